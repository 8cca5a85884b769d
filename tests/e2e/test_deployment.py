"""What an integrator deploys: docker-compose.yml, the Dockerfile, the systemd unit.

There is no container engine here, so the compose file is checked three ways:
Debian's docker-compose validates it (`config`, which needs no engine) and
prints it resolved; that resolved form is held to what a deployment needs (the
simulators on an internal network, nothing of theirs published, health checks,
the server started once its devices are healthy); and each service's command and
health check are run as processes, as the compose file runs them, on loopback.
mosquitto, the cell's MQTT broker, runs from its image's command as Debian's
mosquitto with the mounted configuration, its health check with Debian's mosquitto_sub.
The systemd unit is checked by `systemd-analyze verify` and for its hardening.
"""

from __future__ import annotations

import configparser
import contextlib
import getpass
import re
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml

from server.line.broker import DEMO_PASSWORDS, mosquitto_binary, write_password_file
from tests.processes import ROOT, environment, stop
from tests.serving import free_port

SIMULATORS = ("robot-sim", "glue-sim")
BROKER = "mosquitto"
BROKER_CONFIG_DIR = "/mosquitto/config"
BROKER_CONFIG = f"{BROKER_CONFIG_DIR}/mosquitto.conf"
SIMULATOR_PORTS = {"30003", "5020", "5021"}  # robot, Modbus, the glue simulator's fault channel
INSTALL_HINT = "`make deploy-tools` installs Debian's docker-compose and systemd"


def tool(name: str) -> str:
    found = shutil.which(name)
    assert found, f"{name} is needed by these tests: {INSTALL_HINT}"
    return found


def compose_config(
    tmp_path: Path, compose_file: Path, *overlays: Path, **variables: str
) -> dict[str, Any]:
    """`docker-compose config` of `compose_file` (and `overlays` on top): validated,
    resolved, as YAML."""
    env_file = tmp_path / "compose.env"  # never a stray .env beside the file
    env_file.write_text("".join(f"{k}={v}\n" for k, v in variables.items()))
    files = [word for path in (compose_file, *overlays) for word in ("-f", str(path))]
    answer = subprocess.run(
        [tool("docker-compose"), "--env-file", str(env_file), *files, "config"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={k: v for k, v in environment().items() if not k.startswith("GLUE_HMI_")},
        timeout=120,
    )
    assert answer.returncode == 0, answer.stderr
    return yaml.safe_load(answer.stdout)


@pytest.fixture(scope="module")
def compose(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    # The cell's broker password as an integrator's .env gives it (make-passwd's).
    password = DEMO_PASSWORDS["cell"]
    return compose_config(
        tmp_path_factory.mktemp("compose"),
        ROOT / "docker-compose.yml",
        GLUE_MQTT_CELL_PASSWORD=password,
    )


def test_docker_compose_refuses_a_malformed_file(tmp_path: Path) -> None:
    """The validation the other tests rely on does catch a mistake."""
    broken = tmp_path / "docker-compose.yml"
    text = (ROOT / "docker-compose.yml").read_text()
    broken.write_text(text.replace("      retries: 3\n", "      retries: three\n", 1))
    env_file = tmp_path / "compose.env"
    env_file.write_text("")
    answer = subprocess.run(
        [tool("docker-compose"), "--env-file", str(env_file), "-f", str(broken), "config", "-q"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
    )
    assert answer.returncode != 0
    assert "retries" in answer.stderr


def test_simulators_are_on_an_internal_network_and_publish_nothing(compose) -> None:
    services = compose["services"]
    for name in SIMULATORS:
        assert "ports" not in services[name], name
        assert list(services[name]["networks"]) == ["devices"], name
        assert "--control-port" not in services[name]["command"]  # no fault channel at all
    assert compose["networks"]["devices"]["internal"] is True
    published = [p for s in services.values() for p in s.get("ports", [])]
    # The server's HTTP port and the broker's MQTT port, this host only.
    assert sorted(published) == ["127.0.0.1:1883:1883/tcp", "127.0.0.1:8000:8000/tcp"]
    for port in published:
        assert not SIMULATOR_PORTS & set(re.findall(r"\d+", str(port)))


def test_the_hmi_port_is_published_where_the_integrator_says(tmp_path: Path) -> None:
    chosen = compose_config(
        tmp_path, ROOT / "docker-compose.yml", GLUE_HMI_BIND="0.0.0.0", GLUE_HMI_PORT="8080"
    )
    assert chosen["services"]["server"]["ports"] == ["0.0.0.0:8080:8000/tcp"]


def test_the_broker_port_is_published_where_the_integrator_says(tmp_path: Path) -> None:
    chosen = compose_config(
        tmp_path, ROOT / "docker-compose.yml", GLUE_MQTT_BIND="10.0.0.5", GLUE_MQTT_PORT="1884"
    )
    assert chosen["services"][BROKER]["ports"] == ["10.0.0.5:1884:1883/tcp"]


def test_the_tls_overlay_serves_https_with_the_certificate_and_key_as_secrets(
    tmp_path: Path, compose
) -> None:
    """docker-compose.tls.yml: the server's certificate and key from files on the host,
    mounted as compose secrets (not in the image, not in its environment), and its health
    asked over https; nothing else changes."""
    cert, key = tmp_path / "cell.pem", tmp_path / "cell.key"
    tls = compose_config(
        tmp_path,
        ROOT / "docker-compose.yml",
        ROOT / "docker-compose.tls.yml",
        GLUE_TLS_CERT=str(cert),
        GLUE_TLS_KEY=str(key),
        GLUE_MQTT_CELL_PASSWORD=DEMO_PASSWORDS["cell"],
    )
    server = tls["services"]["server"]
    assert server["environment"]["GLUE_APP_TLS_CERT_FILE"] == "/run/secrets/cell_tls_cert"
    assert server["environment"]["GLUE_APP_TLS_KEY_FILE"] == "/run/secrets/cell_tls_key"
    assert {s if isinstance(s, str) else s["source"] for s in server["secrets"]} == {
        "cell_tls_cert",
        "cell_tls_key",
    }
    assert tls["secrets"] == {
        "cell_tls_cert": {"file": str(cert)},
        "cell_tls_key": {"file": str(key)},
    }
    assert server["healthcheck"]["test"] == [
        "CMD", "python", "-m", "server.cli.healthcheck", "https://127.0.0.1:8000/health"
    ]  # fmt: skip
    plain = compose["services"]["server"]
    assert server["ports"] == plain["ports"] and server["command"] == plain["command"]
    assert {k: v for k, v in server["environment"].items() if "TLS" not in k} == plain[
        "environment"
    ]


def test_the_server_publishes_to_the_composed_broker(compose) -> None:
    services = compose["services"]
    assert services["server"]["environment"]["GLUE_APP_MQTT_URL"] == f"mqtt://{BROKER}:1883"
    assert set(services[BROKER]["networks"]) == {"plant"} <= set(services["server"]["networks"])
    assert services[BROKER]["image"].startswith("eclipse-mosquitto:")
    mounts = {}
    for mount in services[BROKER]["volumes"]:
        source, target, mode = mount.rsplit(":", 2)
        assert mode == "ro", mount
        mounts[target] = Path(source)
    shipped = ROOT / "deploy" / "mosquitto"
    assert mounts == {
        BROKER_CONFIG: shipped / "mosquitto.conf",
        f"{BROKER_CONFIG_DIR}/acl": shipped / "acl",  # the ACL the demo and tests use
        f"{BROKER_CONFIG_DIR}/health.acl": shipped / "health.acl",
        f"{BROKER_CONFIG_DIR}/passwd": shipped / "passwd",  # made by make-passwd, not committed
    }
    # The cell signs in; its password comes from .env, never from the file.
    server_env = services["server"]["environment"]
    assert server_env["GLUE_APP_MQTT_USERNAME"] == "cell"
    assert server_env["GLUE_APP_MQTT_PASSWORD"] == DEMO_PASSWORDS["cell"]  # from .env


def test_the_shipped_broker_refuses_anonymous_clients_and_has_an_acl() -> None:
    config = (ROOT / "deploy" / "mosquitto" / "mosquitto.conf").read_text()
    plant = config.split("listener 1883", 1)[1].split("listener", 1)[0]
    assert "allow_anonymous false" in plant and "acl_file /mosquitto/config/acl" in plant
    assert "password_file /mosquitto/config/passwd" in plant
    assert not (ROOT / "deploy" / "mosquitto" / "passwd").exists() or _ignored("passwd")


def _ignored(name: str) -> bool:
    answer = subprocess.run(
        ["git", "check-ignore", "-q", f"deploy/mosquitto/{name}"], cwd=ROOT, check=False
    )
    return answer.returncode == 0


def test_every_service_is_health_checked_and_the_server_waits_for_its_devices(compose) -> None:
    services = compose["services"]
    for name, service in services.items():
        test = service["healthcheck"]["test"]
        if name == BROKER:  # the broker's image has its own client, no Python
            assert test[:2] == ["CMD", "mosquitto_sub"], test
            continue
        assert test[:4] == ["CMD", "python", "-m", "server.cli.healthcheck"], name
    assert services["server"]["depends_on"] == {
        name: {"condition": "service_healthy"} for name in SIMULATORS
    }


def dockerfile() -> list[tuple[str, str]]:
    """The Dockerfile's instructions, continuation lines joined: (INSTRUCTION, rest)."""
    text = re.sub(r"\\\n", " ", (ROOT / "Dockerfile").read_text())
    lines = [line.strip() for line in text.splitlines()]
    return [
        (line.split(None, 1)[0].upper(), line.split(None, 1)[1])
        for line in lines
        if line and not line.startswith("#")
    ]


def test_the_image_runs_as_an_unprivileged_user_with_a_health_check() -> None:
    instructions = dockerfile()
    users = [rest for kind, rest in instructions if kind == "USER"]
    assert users, "no USER: the server would run as root"
    user = users[-1].split(":")[0]
    assert user not in {"root", "0"}
    last_user = max(i for i, (kind, _) in enumerate(instructions) if kind == "USER")
    assert all(kind != "USER" for kind, _ in instructions[last_user + 1 :])
    created = " ".join(rest for kind, rest in instructions if kind == "RUN")
    assert "useradd --system --uid 10001 --gid glue" in created and user == "glue"
    (health,) = [rest for kind, rest in instructions if kind == "HEALTHCHECK"]
    assert '"server.cli.healthcheck"' in health and "/health" in health
    (command,) = [rest for kind, rest in instructions if kind == "CMD"]
    assert command.startswith('["glue-server"')


# --- the services as processes, as the compose file runs them ---------------------------


class Localized:
    """A service's command as it runs here: loopback for every interface and service name,
    a free port for each published-in-container port, a temporary directory for /data."""

    def __init__(self, compose: dict[str, Any], data: Path) -> None:
        self.hosts = {name: "127.0.0.1" for name in compose["services"]} | {"0.0.0.0": "127.0.0.1"}
        ports = ("30003", "5020", "8000", "1883", "1884")
        self.ports = {port: str(free_port()) for port in ports}
        self.data = data
        self.broker_dir = data.parent / "broker-config"  # no service name in it: see __call__
        self.broker_dir.mkdir(parents=True, exist_ok=True)
        self.broker_config = self.broker_dir / "mosquitto.conf"
        for mount in compose["services"][BROKER]["volumes"]:  # the mounted files, localized
            source, target, _ = mount.rsplit(":", 2)
            local_file = self.broker_dir / Path(target).name
            if target.endswith("/passwd"):  # not committed: made as make-passwd makes it
                write_password_file(local_file, DEMO_PASSWORDS)
            elif target == BROKER_CONFIG:
                lines = Path(source).read_text().splitlines()
                local = [" ".join(self(word) for word in line.split()) for line in lines]
                # Started as root here, mosquitto would drop to its own user, who cannot
                # read this test's directory (in the image it runs as its user already).
                local.insert(0, f"user {getpass.getuser()}")
                self.broker_config.write_text("\n".join(local) + "\n")
            else:
                local_file.write_text(Path(source).read_text())

    def __call__(self, word: str) -> str:
        word = word.replace(f"{BROKER_CONFIG_DIR}/", f"{self.broker_dir}/")  # before the hosts
        for host, local in self.hosts.items():
            word = re.sub(rf"(?<![\w.-]){re.escape(host)}(?![\w.-])", local, word)
        for port, local in self.ports.items():
            word = re.sub(rf"(?<!\d){port}(?!\d)", local, word)
        return str(self.data) if word == "/data" else word

    def argv(self, command: list[str]) -> list[str]:
        """`python ...` and `glue-server ...` with this checkout's interpreter; the broker's
        image's `mosquitto` and `mosquitto_sub` as Debian installs them."""
        if command[0] == "mosquitto":
            assert command[1:] == ["-c", BROKER_CONFIG], command
            return [mosquitto_binary(), "-c", str(self.broker_config)]
        if command[0] == "mosquitto_sub":  # compose's `$$` is a literal `$`
            return [tool("mosquitto_sub"), *(self(w).replace("$$", "$") for w in command[1:])]
        words = [self(word) for word in command]
        if words[0] == "glue-server":
            return [sys.executable, "-m", "server", *words[1:]]
        assert words[0] == "python", words
        return [sys.executable, *words[1:]]


def healthy(local: Localized, service: dict[str, Any]) -> subprocess.CompletedProcess[str]:
    """Run the service's health check command once."""
    kind, *command = service["healthcheck"]["test"]
    assert kind == "CMD"
    return subprocess.run(
        local.argv(command), capture_output=True, text=True, env=environment(), cwd=ROOT
    )


@contextlib.contextmanager
def service_process(
    local: Localized, service: dict[str, Any], log: Path
) -> Iterator[subprocess.Popen[str]]:
    env = environment({k: local(str(v)) for k, v in service.get("environment", {}).items()})
    with log.open("w") as output:
        process = subprocess.Popen(
            local.argv(service["command"]),
            stdout=output,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
            cwd=ROOT,
        )
        try:
            yield process
        finally:
            stop(process)


def wait_healthy(local: Localized, service: dict[str, Any], process: subprocess.Popen[str]) -> None:
    """Until the health check passes; not a performance bound (a fresh server commissions)."""
    deadline = time.monotonic() + 180
    while (answer := healthy(local, service)).returncode != 0:
        assert process.poll() is None, f"the service exited with {process.returncode}"
        assert time.monotonic() < deadline, answer.stdout
        time.sleep(0.2)


def test_each_service_runs_and_passes_its_health_check_as_composed(compose, tmp_path: Path) -> None:
    services = compose["services"]
    local = Localized(compose, tmp_path / "data")
    server = services["server"]
    before = healthy(local, server)
    assert before.returncode == 1 and "unhealthy" in before.stdout  # the check can fail
    assert healthy(local, services[BROKER]).returncode != 0  # no broker yet: this one too
    with contextlib.ExitStack() as running:
        broker = running.enter_context(
            service_process(local, services[BROKER], tmp_path / "mosquitto.log")
        )
        wait_healthy(local, services[BROKER], broker)  # not waited for by the server: first
        for name in server["depends_on"]:  # started first, as service_healthy orders them
            process = running.enter_context(
                service_process(local, services[name], tmp_path / f"{name}.log")
            )
            wait_healthy(local, services[name], process)
        process = running.enter_context(service_process(local, server, tmp_path / "server.log"))
        wait_healthy(local, server, process)
        # The server drives the simulators it was pointed at, through the real clients.
        health = httpx.get(f"http://127.0.0.1:{local.ports['8000']}/health").json()
        assert "RTU over TCP" in health["devices"]["glue"]["link"], health
        assert local.ports["30003"] in str(health["devices"]["robot"]), health
        # Nothing was opened beyond loopback: the simulators' ports are taken on 127.0.0.1.
        # The server was told where its broker is: the composed one, on its local port.
        server_env = Path(f"/proc/{process.pid}/environ").read_bytes()
        assert f"GLUE_APP_MQTT_URL=mqtt://127.0.0.1:{local.ports['1883']}".encode() in server_env
        # It signed in at the broker as `cell` (anonymous clients are refused).
        deadline = time.monotonic() + 60
        while not httpx.get(f"http://127.0.0.1:{local.ports['8000']}/health").json()["mqtt"][
            "connected"
        ]:
            assert time.monotonic() < deadline, "the cell did not sign in at the broker"
            time.sleep(0.2)
        for port in (local.ports["30003"], local.ports["5020"], local.ports["1883"]):
            with socket.create_connection(("127.0.0.1", int(port)), timeout=5):
                pass


# --- the systemd unit --------------------------------------------------------------------

UNIT = ROOT / "deploy" / "glue-server.service"


def unit() -> configparser.ConfigParser:
    parser = configparser.ConfigParser(strict=False, interpolation=None, delimiters=("=",))
    parser.optionxform = str  # type: ignore[assignment,method-assign]  # keys are case-sensitive
    parser.read_string(UNIT.read_text())
    return parser


def test_systemd_verifies_the_unit_without_a_warning(tmp_path: Path) -> None:
    """`systemd-analyze verify` (no running systemd needed) with ExecStart's program where
    it is installed here: any unknown key or bad value is printed, and fails this."""
    installed = tmp_path / "glue-server.service"
    text = UNIT.read_text().replace(
        "/opt/glue-cell/venv/bin/glue-server", str(Path(sys.executable).with_name("glue-server"))
    )
    installed.write_text(text)
    answer = subprocess.run(
        [tool("systemd-analyze"), "verify", "--man=no", str(installed)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert answer.returncode == 0 and answer.stderr == "" and answer.stdout == "", (
        answer.stdout + answer.stderr
    )


def test_systemd_verify_catches_a_mistake(tmp_path: Path) -> None:
    broken = tmp_path / "glue-server.service"
    broken.write_text(UNIT.read_text().replace("NoNewPrivileges=yes", "NoNewPrivilege=yes"))
    answer = subprocess.run(
        [tool("systemd-analyze"), "verify", "--man=no", str(broken)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert "Unknown key" in answer.stderr


def test_the_unit_runs_hardened_as_its_own_user_and_restarts_within_limits() -> None:
    service = unit()["Service"]
    assert service["User"] == "glue-cell" and service["Group"] == "glue-cell"
    for key, value in {
        "NoNewPrivileges": "yes",
        "ProtectSystem": "strict",
        "ProtectHome": "yes",
        "PrivateTmp": "yes",
        "StateDirectory": "glue-cell",
        "StateDirectoryMode": "0700",
        "ReadWritePaths": "/var/lib/glue-cell",
        "Restart": "on-failure",
        "CapabilityBoundingSet": "",
    }.items():
        assert service[key] == value, key
    assert "--data-dir /var/lib/glue-cell" in service["ExecStart"]
    assert service["EnvironmentFile"] == "-/etc/glue-cell/glue-server.env"
    limits = unit()["Unit"]
    assert int(limits["StartLimitBurst"]) >= 1 and int(limits["StartLimitIntervalSec"]) > 0
    env_file = (ROOT / "deploy" / "glue-server.env").read_text()
    assert "GLUE_HTTP_HOST=127.0.0.1" in env_file
    # https shown, off until a certificate is there (a missing file stops the start).
    assert "\n#GLUE_APP_TLS_CERT_FILE=/etc/glue-cell/" in env_file
    assert "\n#GLUE_APP_TLS_KEY_FILE=/etc/glue-cell/" in env_file


def test_one_image_is_built_once_and_every_log_is_bounded(compose) -> None:
    """The server's service builds the image; the simulators run it as built, never
    pulled nor built again; each container's log is rotated, not left to fill the disk."""
    services = compose["services"]
    image = services["server"]["image"]
    assert "build" in services["server"]
    for name in SIMULATORS:
        assert "build" not in services[name], name
        assert services[name]["image"] == image, name
        assert services[name]["pull_policy"] == "never", name
    for name, service in services.items():
        logging = service["logging"]
        assert logging["driver"] == "json-file", name
        assert logging["options"] == {"max-size": "10m", "max-file": "3"}, name


def test_the_device_mapping_of_a_real_cell_is_in_the_compose_file() -> None:
    """A USB camera and a serial dispenser: the lines to uncomment are where they apply."""
    text = (ROOT / "docker-compose.yml").read_text()
    server = text.split("\n  server:\n", 1)[1].split("\n  mosquitto:\n", 1)[0]
    for line in ("# devices:", "#   - /dev/video0:/dev/video0", "#   - /dev/ttyUSB0:/dev/ttyUSB0"):
        assert line in server, line
