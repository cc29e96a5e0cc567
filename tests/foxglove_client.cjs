// A Foxglove WebSocket client no one here wrote (@foxglove/ws-protocol over ws), for
// tests/test_foxglove.py:
//
//   node foxglove_client.cjs URL SECONDS TOPIC... [--set NAME=VALUE] [--param NAME=VALUE]
//
// Connects with the subprotocol foxglove.sdk.v1 (the SDK's server refuses the library's
// own foxglove.websocket.v1), subscribes to each TOPIC as it is advertised, and once every
// TOPIC but /events and /set brought a message publishes --set on /set ({"name", "value"}) and sets --param
// as a parameter.  Prints one JSON line per event (advertised channels, messages with
// their log time as text, status messages, parameter values) and a summary; exits 0
// after SECONDS, 2 where a TOPIC but /events and /set brought nothing by then, 3 where it could not connect.
"use strict";
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const WebSocket = require("ws");

const args = process.argv.slice(2);
const url = args.shift();
const seconds = Number(args.shift());
const topics = [];
const sets = [];
const params = [];
while (args.length) {
  const a = args.shift();
  if (a === "--set" || a === "--param") {
    const [name, value] = args.shift().split("=");
    (a === "--set" ? sets : params).push({ name, value: Number(value) });
  } else {
    topics.push(a);
  }
}
const out = (doc) => process.stdout.write(JSON.stringify(doc) + "\n");
const counts = Object.fromEntries(topics.map((t) => [t, 0]));
// events come when they happen, and /set carries the writes this client is to make
const gating = topics.filter((t) => t !== "/events" && t !== "/set");
const bySub = new Map();
let wrote = false;

const ws = new WebSocket(url, ["foxglove.sdk.v1"]);
const client = new FoxgloveClient({ ws });
ws.on("error", (err) => {
  out({ error: String(err) });
  process.exit(3);
});
client.on("serverInfo", (info) => out({ serverInfo: info }));
client.on("status", (s) => out({ status: s }));
client.on("parameterValues", (p) => out({ parameterValues: p.parameters }));
client.on("advertise", (channels) => {
  for (const ch of channels) {
    out({ advertise: { topic: ch.topic, encoding: ch.encoding, schemaName: ch.schemaName,
                       schemaEncoding: ch.schemaEncoding, schema: ch.schema } });
    if (topics.includes(ch.topic)) {
      bySub.set(client.subscribe(ch.id), ch.topic);
    }
  }
});
client.on("message", ({ subscriptionId, timestamp, data }) => {
  const topic = bySub.get(subscriptionId);
  const text = Buffer.from(data.buffer, data.byteOffset, data.byteLength).toString();
  counts[topic] += 1;
  if (counts[topic] <= 400) {
    out({ topic, log_time: timestamp.toString(), message: JSON.parse(text) });
  }
  if (!wrote && gating.every((t) => counts[t] > 0)) {
    wrote = true;
    if (sets.length) {
      const channel = client.advertise({ topic: "/set", encoding: "json",
                                         schemaName: "ucom.Set" });
      for (const s of sets) {
        client.sendMessage(channel, new TextEncoder().encode(JSON.stringify(s)));
      }
      out({ sent: sets });
    }
    if (params.length) {
      client.setParameters(params, "set-1");
      out({ setParameters: params });
    }
  }
});
setTimeout(() => {
  out({ summary: counts });
  client.close();
  process.exit(gating.every((t) => counts[t] > 0) ? 0 : 2);
}, seconds * 1000);
