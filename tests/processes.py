"""Tier three: the simulators and the server as separate processes on loopback.

The bounds on a process coming up are not performance assertions: a fresh server
commissions its simulated cell first (camera and robot calibration, CPU-bound),
which takes many times longer on a machine busy with other work.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import ssl
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import httpx

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class Running:
    process: subprocess.Popen[str]
    port: int
    extra_ports: dict[str, int]


def _env(extra: dict[str, str] | None) -> dict[str, str]:
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith(("GLUE_APP_", "ROBOT_IP", "VISION_CAMERA_ID", "GLUE_CONTROLLER_PORT"))
    }
    env["PYTHONPATH"] = str(ROOT)
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra or {})
    return env


@contextlib.contextmanager
def simulator(module: str, *args: str, timeout: float = 60.0) -> Iterator[Running]:
    """Run `python -m module --port 0 ...`; read the ports it prints ("... on HOST:PORT")."""
    process = subprocess.Popen(
        [sys.executable, "-m", module, "--port", "0", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=_env(None),
        cwd=ROOT,
    )
    ports: dict[str, int] = {}
    deadline = time.monotonic() + timeout
    try:
        assert process.stdout is not None
        while time.monotonic() < deadline:
            line = process.stdout.readline()
            if not line:
                raise RuntimeError(f"{module} exited with {process.wait()} before listening")
            match = re.search(r"(\w+) on [\d.]+:(\d+)", line)
            if match:
                ports[match.group(1)] = int(match.group(2))
            if "listening on" in line:
                break
        else:
            raise RuntimeError(f"{module} did not start listening within {timeout} s")
        yield Running(process, ports["listening"], ports)
    finally:
        stop(process)


def has_ended(pid: int) -> bool:
    """The process is gone, or only its exit status is left for its parent (Linux /proc)."""
    stat = Path(f"/proc/{pid}/stat")
    try:
        return stat.read_text().split()[2] == "Z"
    except FileNotFoundError:
        return True


def stop(process: subprocess.Popen[str]) -> None:
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(5)


# A test's port is free when picked, not reserved: see server_process.
BIND_RETRIES = 2
# What every served process gets unless the test sets it. vision_processing_timeout
# (5 s by default) also bounds the camera coming up at start, and the simulated camera's
# image process is a fresh Python importing NumPy and OpenCV: on a machine busy with
# other work (the suite's other workers, other jobs) that took longer, and the cell
# started in ERROR. No test waits for that timeout to fire, so it is set far from any
# start-up, as the rig's cells have it (tests/rig.py, VISION_TIMEOUT).
SERVED = {"GLUE_APP_VISION_PROCESSING_TIMEOUT": "30"}
# A served cell whose simulated devices run ten times faster: its first start commissions
# the cell (the robot calibration moves the arm to each pose) in a tenth of the time, and
# so does any move. For the tests that are about what survives a kill or a restart, not
# about how long a move lasts.
FAST_DEVICES = {"GLUE_APP_SIMULATION_SPEED_FACTOR": "10"}


@contextlib.contextmanager
def server_process(
    port: int,
    data_dir: Path,
    env: dict[str, str] | None = None,
    timeout: float = 120.0,
    *,
    log_path: Path | None = None,
    preexec_fn: Callable[[], None] | None = None,
    ca_file: Path | None = None,
) -> Iterator[subprocess.Popen[str]]:
    """Run `python -m server` on `port`; wait until GET /health answers.

    `env` adds to (or overrides) `SERVED`. Its output goes to `log_path` (default
    `<data_dir>/server.log`); `preexec_fn`
    runs in the child before the server (e.g. to set a resource limit). With
    `ca_file` the server serves https (GLUE_APP_TLS_*) and is asked over https,
    trusting that CA.
    """
    log_path = log_path or data_dir / "server.log"
    log = log_path.open("w")
    argv = [sys.executable, "-m", "server", "--port", str(port), "--data-dir", str(data_dir)]

    def start() -> subprocess.Popen[str]:
        return subprocess.Popen(
            argv,
            stdout=log,
            stderr=subprocess.STDOUT,
            text=True,
            env=_env({**SERVED, **(env or {})}),
            cwd=ROOT,
            preexec_fn=preexec_fn,
        )

    process = start()
    retries = BIND_RETRIES
    scheme = "https" if ca_file else "http"
    verify = ssl.create_default_context(cafile=str(ca_file)) if ca_file else True
    try:
        # One client for every poll: a new one per poll loads the system's CA certificates
        # again (~25 ms of CPU each, ten times a second, beside the server starting up).
        with httpx.Client(timeout=1, verify=verify) as poller:
            deadline = time.monotonic() + timeout
            while True:
                if process.poll() is not None:
                    output = log_path.read_text()
                    if retries and f"('127.0.0.1', {port}): address already in use" in output:
                        # `port` was free when picked, then a socket bound to port 0 inside
                        # that very server (a simulator) was given it first; again, same port.
                        retries -= 1
                        process = start()
                        continue
                    raise RuntimeError(f"server exited with {process.returncode}: {output[-2000:]}")
                try:
                    poller.get(f"{scheme}://127.0.0.1:{port}/health").raise_for_status()
                    break
                except httpx.HTTPError:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.1)
        yield process
    finally:
        stop(process)
        log.close()


class Child(Protocol):
    """What a readiness wait reads of a child process (subprocess's Popen or psutil's)."""

    args: Any
    returncode: int | None

    def poll(self) -> int | None: ...


def wait_answering(process: Child, url: str, within: float, *, log: Path | None = None) -> None:
    """Until GET `url` answers 2xx; RuntimeError if `process` exits first (with the end of
    its `log`, if given) or `within` s pass.

    One client for every poll: a new one per poll loads the system's CA certificates again
    (~25 ms of CPU each, ten times a second, beside the server starting up)."""
    deadline = time.monotonic() + within
    with httpx.Client(timeout=1) as poller:
        while True:
            if process.poll() is not None:
                tail = f":\n{log.read_text(errors='replace')[-2000:]}" if log else ""
                raise RuntimeError(f"{process.args} exited with {process.returncode}{tail}")
            with contextlib.suppress(httpx.HTTPError):
                poller.get(url).raise_for_status()
                return
            if time.monotonic() > deadline:
                raise RuntimeError(f"{url} did not answer within {within:g} s")
            time.sleep(0.1)


def run_module(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    """Run `python -m ARGS` to its end (a CLI such as `server backup`), output captured."""
    return run_python("-m", *args, timeout=timeout)


def run_python(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    """Run `python ARGS` to its end (`-c CODE`, a script), in this checkout, output captured."""
    return subprocess.run(
        [sys.executable, *args],
        capture_output=True,
        text=True,
        env=_env(None),
        cwd=ROOT,
        timeout=timeout,
    )


def environment(extra: dict[str, str] | None = None) -> dict[str, str]:
    """The environment a test's child process gets: this checkout first on the path, no
    cell settings inherited from the shell, then `extra`."""
    return _env(extra)
