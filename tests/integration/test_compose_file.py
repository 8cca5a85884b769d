"""docker-compose.yml describes the same three processes the e2e tests start.

No Docker engine runs here, so the compose file is checked as data: it parses,
names the services, and each command is one the process-level tests run.
"""

from __future__ import annotations

from pathlib import Path

import yaml

from server.__main__ import parse_args
from server.bootstrap.devices import parse_tcp_address
from server.config import Settings
from tests.processes import simulator

ROOT = Path(__file__).resolve().parents[2]


def compose() -> dict:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text(encoding="utf-8"))


def test_services_ports_and_commands() -> None:
    services = compose()["services"]
    assert set(services) == {"server", "robot-sim", "glue-sim"}
    assert services["robot-sim"]["command"][:3] == ["python", "-m", "server.drivers.sim.robot_sim"]
    assert services["glue-sim"]["command"][:3] == ["python", "-m", "server.drivers.sim.glue_sim"]
    assert "30003:30003" in services["robot-sim"]["ports"]
    assert "5020:5020" in services["glue-sim"]["ports"]
    assert services["server"]["command"][0] == "glue-server"
    args = parse_args(services["server"]["command"][1:])
    assert (args.host, args.port) == ("0.0.0.0", 8000)


def test_server_environment_points_at_the_simulators(monkeypatch) -> None:
    environment = compose()["services"]["server"]["environment"]
    for key, value in environment.items():
        monkeypatch.setenv(key, str(value))
    settings = Settings()
    assert settings.robot_ip == "robot-sim" and settings.robot_port == 30003
    assert parse_tcp_address(settings.glue_controller_port) == ("glue-sim", 5020)
    assert settings.camera_simulated


def test_the_compose_commands_start_real_simulators() -> None:
    """Each simulator command of the compose file, on loopback, really listens."""
    services = compose()["services"]
    for service in ("robot-sim", "glue-sim"):
        command = services[service]["command"]
        module = command[command.index("-m") + 1]
        args = command[command.index("-m") + 2 :]
        args[args.index("--host") + 1] = "127.0.0.1"
        del args[args.index("--port") : args.index("--port") + 2]
        if "--control-port" in args:
            args[args.index("--control-port") + 1] = "0"
        with simulator(module, *args) as running:
            assert running.port > 0


def test_dockerfile_installs_the_package_and_runs_the_console_script() -> None:
    dockerfile = (ROOT / "Dockerfile").read_text(encoding="utf-8")
    assert "pip install" in dockerfile and "-c constraints.txt" in dockerfile
    assert 'CMD ["glue-server"' in dockerfile
