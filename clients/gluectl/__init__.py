"""gluectl: drive and watch the glue cell from a shell or a script.

    gluectl state                        where the cell is, what it may do next
    gluectl start --workpiece demo       spray (202 → exit 0; refused → exit 3)
    gluectl wait IDLE --timeout 120      block until the cell is back in IDLE
    gluectl watch                        live view: progress bar and state timeline
    gluectl order start demo 20          make 20 good parts, one run after another
    gluectl settings set shift_hours=10  change a runtime setting; it stays over a restart
    gluectl line --broker mqtt://host:1883   every cell of a line, live from the broker
    gluectl --json history --limit 5     anything as JSON (--json before or after the command)
    gluectl --mqtt mqtt://broker:1883 --cell-id cell-1 start   the same command, signed, over MQTT

Global options go before the command: --url (env GLUE_CELL_URL, default
http://127.0.0.1:8000), --token (env GLUE_CELL_TOKEN, else <data dir>/admin.token),
--data-dir (env GLUE_APP_DATA_PATH, default ./data), --ca-file (env
GLUE_CELL_CA_FILE: the CA an https server's certificate must chain to), --json. With
--mqtt (env GLUE_MQTT_URL) the commands (start, pause, resume, cancel, estop, reset,
home, jog, calibrations, create-workpiece) go to --cell-id over the broker instead,
signed with the token (clients/client/mqtt_commands.py), and the answer is printed as
over HTTP; --mqtt-user, --mqtt-password (env GLUE_MQTT_PASSWORD, or
--mqtt-password-file), --mqtt-ca-file and --mqtt-prefix say how to reach the broker
(docs/cli.md).

Exit codes, stable for scripts (the reason is printed on stderr):

    0  accepted / ok
    1  an unexpected answer (e.g. a 500), never a documented outcome
    2  usage error: unknown option, bad argument (typer's)
    3  refused (409): the command is not allowed in the current state;
       `allowed` exits 3 when the answer is no
    4  unauthorized or forbidden (401/403): no valid token, or the role is too low
    5  unreachable: no connection, or no answer in time
    6  invalid request (422), or not found (404)
    7  busy (503): the event queue is full or the journal cannot write; retry shortly
    8  timeout in `wait`
    9  `wait`: the cell is in ERROR, which only a reset leaves (even if it was
       already there); --no-fail-on-error waits through it for someone's reset

With --json every command prints one JSON document on stdout, errors too
(`{"error": "Refused", "status_code": 409, "message": ...}`), usage errors
included (`{"error": "UsageError", ...}`, exit 2); `watch --json` prints one
message per line. `gluectl --version` prints the package's version.

The package: `cli` puts the command line together (the typer app and the entry point
`main`); `options` reads the global options; `calls` sends a query or a command and
prints its answer or error; `exit_codes` maps errors to the codes above; `format`
holds the text forms every table shares; the commands live by concern in `cell`,
`workpieces`, `orders`, `reports`, `settings`, `watch` and `line`.
"""

from __future__ import annotations

from clients.gluectl.cli import main

__all__ = ["main"]
