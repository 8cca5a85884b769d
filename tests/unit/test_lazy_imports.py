"""A server with a feature off does not load what only that feature uses.

OPC UA (asyncua), MQTT (aiomqtt, paho), TLS's certificate checks
(cryptography) and the webhooks' HTTP client (httpx, with the rich and click it
brings) cost the server memory and start-up time for nothing when their
settings are unset, which is the default; each is imported where the feature
is built (`server/bootstrap/plant.py`, `server/bootstrap/tls.py`,
`server/notify/notifier.py: Notifier.start`).
"""

from __future__ import annotations

from tests.processes import run_python

ONLY_WHEN_ASKED_FOR = ("asyncua", "aiomqtt", "paho", "cryptography", "httpx", "rich")

PROBE = """
import sys
import server.__main__
from server.bootstrap.app import create_app
print(" ".join(sorted({name.split(".")[0] for name in sys.modules})))
"""


def test_the_server_loads_no_plant_link_tls_nor_webhook_library_it_was_not_asked_for() -> None:
    done = run_python("-c", PROBE)
    assert done.returncode == 0, done.stderr
    loaded = set(done.stdout.split())
    assert not loaded & set(ONLY_WHEN_ASKED_FOR), sorted(loaded & set(ONLY_WHEN_ASKED_FOR))
