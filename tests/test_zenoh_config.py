"""``--zenoh-config``: a full Zenoh configuration on both sides (issue 18, 1): the robot
listens on TLS only, a browser that trusts the robot's certificate authority reads and
sets its edges, one without it finds no robot (exit 4); access control in the robot's
configuration refuses the network's writes before they reach the loop.  The
certificates are made for the test with openssl (skipped where it is missing)."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.helpers import terminate

from .test_zenoh import SENSOR, TARGET, _free_port, _ucom, flashed  # noqa: F401

LOCAL = "127.0.0.1"


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True,
                   timeout=30)


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A certificate authority and the robot's certificate for 127.0.0.1, signed by it."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed: no certificates for the TLS test")
    d = tmp_path_factory.mktemp("pki")
    ec = ("-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes")
    _openssl("req", "-x509", *ec, "-keyout", "ca.key", "-out", "ca.pem", "-days", "2",
             "-subj", "/CN=ucom-tools test CA", cwd=d)
    _openssl("req", *ec, "-keyout", "robot.key", "-out", "robot.csr", "-subj",
             "/CN=localhost", cwd=d)
    (d / "san.cnf").write_text(f"subjectAltName=IP:{LOCAL},DNS:localhost\n")
    _openssl("x509", "-req", "-in", "robot.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
             "-CAcreateserial", "-out", "robot.pem", "-days", "2", "-extfile", "san.cnf",
             cwd=d)
    return d


def _write(path: Path, document: dict[str, object]) -> Path:
    path.write_text(json.dumps(document, indent=2))  # JSON is JSON5
    return path


def _robot_config(pki: Path, endpoint: str, **extra: object) -> dict[str, object]:
    return {"mode": "peer", "listen": {"endpoints": [endpoint]},
            "transport": {"link": {"tls": {
                "listen_certificate": str(pki / "robot.pem"),
                "listen_private_key": str(pki / "robot.key")}}}, **extra}


def _browser_config(pki: Path | None, endpoint: str) -> dict[str, object]:
    c: dict[str, object] = {"mode": "peer", "connect": {"endpoints": [endpoint]}}
    if pki is not None:
        c["transport"] = {"link": {"tls": {"root_ca_certificate": str(pki / "ca.pem")}}}
    return c


ROOT = Path(__file__).resolve().parent.parent


class ConfiguredRobot:
    """``ucom remote run armar3 --virtual armar3 --zenoh-config FILE`` (no --zenoh: the
    file's endpoints) in a process of its own, on a copy of the flashed state."""

    def __init__(self, state: Path, tmp: Path, config_file: Path, endpoint: str,
                 *extra: str) -> None:
        self.endpoint = endpoint
        self.state = tmp / "state"
        shutil.copytree(state, self.state)
        self.err_path = tmp / "robot.err"
        with open(self.err_path, "w") as err:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "ucom_tools", "remote", "run", "armar3", "--virtual",
                 "armar3", "--state", str(self.state), "--zenoh-config", str(config_file),
                 *extra], stdout=subprocess.DEVNULL, stderr=err, cwd=ROOT,
                env={**os.environ, "PYTHONPATH": str(ROOT)})

    def ready(self, *browse_args: str) -> None:
        """Once ``ucom browse BROWSE_ARGS`` finds the robot (AssertionError when the
        robot's process ended first or it takes longer than 60 s)."""
        for _ in range(30):
            r = _ucom("browse", "armar3", *browse_args, "--timeout", "2", "--get", SENSOR)
            if r.returncode == 0:
                return
            if self.proc.poll() is not None:
                break
        raise AssertionError("no robot: " + self.err_path.read_text())

    def stop(self) -> None:
        terminate(self.proc)


@pytest.fixture(scope="module")
def tls_robot(flashed: Path, pki: Path,  # noqa: F811
              tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[ConfiguredRobot,
                                                                          Path]]:
    tmp = tmp_path_factory.mktemp("tls")
    endpoint = f"tls/{LOCAL}:{_free_port()}"
    robot_file = _write(tmp / "robot.json5", _robot_config(pki, endpoint))
    browser_file = _write(tmp / "browser.json5", _browser_config(pki, endpoint))
    r = ConfiguredRobot(flashed, tmp, robot_file, endpoint, "--allow-writes")
    try:
        r.ready("--zenoh-config", str(browser_file))
        yield r, browser_file
    finally:
        r.stop()


def test_a_browser_that_trusts_the_robots_authority_reads_and_sets_over_tls(
        tls_robot: tuple[ConfiguredRobot, Path]) -> None:
    _, browser_file = tls_robot
    r = _ucom("browse", "armar3", "--zenoh-config", str(browser_file), "--get", SENSOR)
    assert r.returncode == 0, r.stderr
    assert re.search(rf"^{SENSOR} = -?\d+ counts$", r.stdout, re.M), r.stdout
    r = _ucom("browse", "armar3", "--zenoh-config", str(browser_file),
              "--set", f"{TARGET}=500", "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["set"][0]["value"] == 500


def test_a_browser_without_the_authority_finds_no_robot(
        tls_robot: tuple[ConfiguredRobot, Path], tmp_path: Path) -> None:
    robot, _ = tls_robot
    untrusting = _write(tmp_path / "plain.json5", _browser_config(None, robot.endpoint))
    r = _ucom("browse", "armar3", "--zenoh-config", str(untrusting), "--timeout", "2",
              "--get", SENSOR)
    assert r.returncode == 4, (r.returncode, r.stderr)
    assert "no robot" in r.stderr and r.stdout == ""
    plain_tcp = robot.endpoint.replace("tls/", "tcp/")
    r = _ucom("browse", "armar3", "--zenoh", plain_tcp, "--timeout", "2", "--get", SENSOR)
    assert r.returncode == 4, (r.returncode, r.stderr)


def test_access_control_in_the_robots_configuration_refuses_network_writes(
        flashed: Path, tmp_path: Path) -> None:  # noqa: F811
    endpoint = f"tcp/{LOCAL}:{_free_port()}"
    acl = {"enabled": True, "default_permission": "allow",
           "rules": [{"id": "no-writes", "messages": ["query"], "flows": ["ingress"],
                      "permission": "deny", "key_exprs": ["ucom/*/set", "ucom/*/stop"]}],
           "subjects": [{"id": "tcp-peers", "link_protocols": ["tcp"]}],
           "policies": [{"rules": ["no-writes"], "subjects": ["tcp-peers"]}]}
    robot_file = _write(tmp_path / "robot.json5",
                        {"mode": "peer", "listen": {"endpoints": [endpoint]},
                         "access_control": acl})
    robot = ConfiguredRobot(flashed, tmp_path, robot_file, endpoint, "--allow-writes")
    try:
        robot.ready("--zenoh", endpoint)
        r = _ucom("browse", "armar3", "--zenoh", endpoint, "--get", TARGET)
        assert r.returncode == 0 and f"{TARGET} = 0 counts" in r.stdout, r.stderr
        r = _ucom("browse", "armar3", "--zenoh", endpoint, "--timeout", "2",
                  "--set", f"{TARGET}=500")
        # the query never reaches the robot: the browser says so (a bus error, exit 4)
        assert r.returncode == 4 and "did not answer" in r.stderr, (r.returncode, r.stderr)
        r = _ucom("browse", "armar3", "--zenoh", endpoint, "--get", TARGET)
        assert f"{TARGET} = 0 counts" in r.stdout, (r.stdout, r.stderr)
        assert robot.proc.poll() is None, "the robot's loop ended"
    finally:
        robot.stop()


def test_the_pages_configuration_examples_are_zenoh_configurations() -> None:
    import zenoh

    page = (ROOT / "man/ucom-network.7").read_text()
    examples = re.findall(r"^(robot|browser)\.json5: +(\{.*?\} \} \} \})$",
                          page.replace("\\-", "-"), re.M | re.S)
    assert [name for name, _ in examples] == ["robot", "browser"]
    for _, text in examples:
        c = zenoh.Config.from_json5(text)
        assert "tls/10.0.0.3:7447" in str(c.get_json("listen/endpoints")) + \
            str(c.get_json("connect/endpoints"))
