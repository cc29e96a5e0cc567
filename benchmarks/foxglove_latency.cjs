// The Foxglove client of benchmarks/record.py (@foxglove/ws-protocol over ws, as
// tests/foxglove_client.cjs): subscribes to every channel the server advertises and, per
// topic, takes each message's delivery latency (its arrival on this host's wall clock
// minus its log time, the frames' bus time mapped to the wall clock), for SECONDS.
//
//   node foxglove_latency.cjs URL SECONDS
//
// Prints one JSON line, after SECONDS or at SIGTERM: {topic: {count, p50_ms, p99_ms}} and
// "all".
"use strict";
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const WebSocket = require("ws");

const [url, seconds] = [process.argv[2], Number(process.argv[3])];
const lat = new Map(); // topic -> latencies (ms)
const bySub = new Map();
const ws = new WebSocket(url, ["foxglove.sdk.v1"]);
const client = new FoxgloveClient({ ws });
ws.on("error", (err) => {
  process.stdout.write(JSON.stringify({ error: String(err) }) + "\n");
  process.exit(3);
});
client.on("advertise", (channels) => {
  for (const ch of channels) {
    bySub.set(client.subscribe(ch.id), ch.topic);
    lat.set(ch.topic, []);
  }
});
client.on("message", ({ subscriptionId, timestamp }) => {
  const now = BigInt(Date.now()) * 1000000n + BigInt(Math.round((performance.now() % 1) * 1e6));
  lat.get(bySub.get(subscriptionId)).push(Number(now - timestamp) / 1e6);
});
const pct = (xs, p) => {
  if (!xs.length) return null;
  const s = [...xs].sort((a, b) => a - b);
  return Math.round(s[Math.min(s.length - 1, Math.floor((p / 100) * s.length))] * 1000) / 1000;
};
const finish = () => {
  const out = {};
  const all = [];
  for (const [topic, xs] of lat) {
    out[topic] = { count: xs.length, p50_ms: pct(xs, 50), p99_ms: pct(xs, 99) };
    for (const x of xs) all.push(x); // (a spread of 250,000 arguments overflows the stack)
  }
  out.all = { count: all.length, p50_ms: pct(all, 50), p99_ms: pct(all, 99) };
  process.stdout.write(JSON.stringify(out) + "\n");
  client.close();
  process.exit(0);
};
process.on("SIGTERM", finish); // the benchmark's run ended: the figures so far
setTimeout(finish, seconds * 1000);
