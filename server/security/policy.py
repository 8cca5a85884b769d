"""The access policy: which role each route needs, declared once.

The command routes' roles come from the command catalogue
(server/commands/catalogue.py), the one place a command is declared; the
table below holds every other route.

`None` means open to anyone: the health check and the dashboard's page (its
assets under OPEN_PREFIXES); nothing else.
A route missing from the table needs ADMIN: new routes are closed until
someone decides otherwise. The software stop is open to every authenticated
principal, whatever its role: nobody must be unable to stop the cell.
"""

from __future__ import annotations

from types import MappingProxyType
from typing import Final

from starlette.routing import compile_path

from server.commands.catalogue import CATALOGUE
from server.security.tokens import Role

VIEW, OPER, MAINT, ADMIN = Role.VIEWER, Role.OPERATOR, Role.MAINTENANCE, Role.ADMIN

# The commands' routes take their roles from the command catalogue, where each
# command is declared once; the rest are here.
_ROUTES: Final = MappingProxyType(
    {
        # open
        ("GET", "/health"): None,
        ("GET", "/"): None,  # the operator dashboard's page (it asks for a token itself)
        # viewer: look, and stop
        ("GET", "/openapi.json"): VIEW,  # also in the repository, for integrators
        ("GET", "/state"): VIEW,
        ("GET", "/me"): VIEW,  # who is signed in and what the token may do
        ("GET", "/operations/{name}/allowed"): VIEW,
        ("GET", "/history"): VIEW,
        ("GET", "/operations"): VIEW,
        ("GET", "/errors"): VIEW,
        ("GET", "/errors/{seq}"): VIEW,
        ("GET", "/events"): VIEW,
        # one CSV route per journal table, each with that table's own filters
        ("GET", "/export/events.csv"): VIEW,
        ("GET", "/export/transitions.csv"): VIEW,
        ("GET", "/export/operations.csv"): VIEW,
        ("GET", "/export/errors.csv"): VIEW,
        ("GET", "/export/recoveries.csv"): VIEW,
        ("GET", "/kpis"): VIEW,
        ("GET", "/quality/trends"): VIEW,
        ("GET", "/reports"): VIEW,
        ("GET", "/reports/{report_id}"): VIEW,
        ("GET", "/metrics"): VIEW,
        ("GET", "/calibration"): VIEW,
        ("GET", "/calibration/image"): VIEW,
        ("GET", "/calibration/markers"): VIEW,
        ("GET", "/camera/frame"): VIEW,
        ("GET", "/trajectory"): VIEW,
        ("GET", "/runs/{run_id}/inspection"): VIEW,
        ("GET", "/runs/{run_id}/inspection.jpg"): VIEW,
        ("GET", "/runs/{run_id}/recording"): VIEW,
        ("GET", "/orders"): VIEW,
        ("GET", "/orders/{order_id}"): VIEW,
        ("GET", "/orders/{order_id}/report"): VIEW,
        ("GET", "/workpieces"): VIEW,
        ("GET", "/maintenance"): VIEW,
        ("GET", "/workpieces/{workpiece_id}"): VIEW,
        ("GET", "/workpieces/{workpiece_id}/thumbnail"): VIEW,
        ("POST", "/ws-ticket"): VIEW,
        # operator: run production (the commands' routes: the catalogue)
        ("POST", "/orders"): OPER,
        ("POST", "/orders/{order_id}/close"): OPER,
        ("POST", "/orders/{order_id}/resume"): OPER,
        # maintenance: calibrate, recover, edit the library
        # the camera set-up view's status; its stream, WebSocket /camera/preview/ws, checks
        # the same role at its handshake (server/api/camera_preview.py)
        ("GET", "/camera/preview"): MAINT,
        # the diagnostic bundle: settings (secrets masked), faults, logs, health
        ("GET", "/diagnostics"): MAINT,
        ("POST", "/maintenance/{item}/done"): MAINT,
        ("POST", "/glue/refill"): MAINT,
        ("POST", "/calibration/markers/draft/{marker}/teach"): MAINT,
        ("PUT", "/calibration/markers/draft/{marker}"): MAINT,
        ("DELETE", "/calibration/markers/draft"): MAINT,
        ("POST", "/calibration/markers/apply"): MAINT,
        ("POST", "/workpieces"): MAINT,
        ("PUT", "/workpieces/{workpiece_id}"): MAINT,
        ("DELETE", "/workpieces/{workpiece_id}"): MAINT,
        # admin
        ("GET", "/settings"): ADMIN,
        ("PATCH", "/settings"): ADMIN,
        ("GET", "/tokens"): ADMIN,
        ("POST", "/tokens"): ADMIN,
        ("DELETE", "/tokens/{token_id}"): ADMIN,
        ("GET", "/audit"): ADMIN,
        ("GET", "/audit.csv"): ADMIN,
        ("GET", "/webhooks"): ADMIN,  # names the plant's receivers (redacted)
        ("GET", "/webhooks/deliveries"): ADMIN,
    }
)
POLICY: Final = MappingProxyType(
    {**_ROUTES, **{("POST", spec.path): spec.role for spec in CATALOGUE}}
)
WEBSOCKET_ROLE: Final = VIEW


# The dashboard's static assets (its page, GET /, is in the table): plain files, open.
OPEN_PREFIXES: Final = ("/hmi/",)


def required_role(method: str, path: str) -> Role | None:
    """The role a route needs (None: open), by its path template; unknown routes need ADMIN."""
    method = "GET" if method == "HEAD" else method
    return POLICY.get((method, path), Role.ADMIN)


# Templated paths matched by the router's own compiler, so gate and router agree.
_EXACT: Final = {key: role for key, role in POLICY.items() if "{" not in key[1]}
_TEMPLATED: Final = tuple(
    (method, compile_path(template)[0], role)
    for (method, template), role in POLICY.items()
    if "{" in template
)


def _least(roles: list[Role | None]) -> Role | None:
    """The least of some roles, None (open) below every role; ADMIN of none."""
    if not roles:
        return Role.ADMIN
    return None if None in roles else min(role for role in roles if role is not None)


def _options_role(path: str) -> Role | None:
    """OPTIONS tells which methods a path answers: it needs the least of their roles.

    So whoever may use one of the path's methods may ask which there are, and
    nobody learns more of a path than a method they may use would show.
    """
    if path.startswith(OPEN_PREFIXES):
        return None
    roles = [role for (_, entry), role in _EXACT.items() if entry == path]
    roles += [role for _, pattern, role in _TEMPLATED if pattern.match(path)]
    return _least(roles)


def role_for_request(method: str, path: str) -> Role | None:
    """The role a request needs, from its concrete path (None: open).

    The gate checks before routing, so it matches the path itself: exact paths
    by lookup, templated ones by their regex. A path no entry matches needs
    ADMIN (the app then answers 404): new routes stay closed until the table
    names them. HEAD needs what GET needs; OPTIONS, and a method the path does
    not answer (405), the least of what the path's methods need.
    """
    if method == "OPTIONS":
        return _options_role(path)
    method = "GET" if method == "HEAD" else method
    if (method, path) in _EXACT:
        return _EXACT[(method, path)]
    for entry_method, pattern, templated_role in _TEMPLATED:
        if entry_method == method and pattern.match(path):
            return templated_role
    if method == "GET" and path.startswith(OPEN_PREFIXES):
        return None
    # A method the table does not name: no route answers it (tests/integration/test_access.py
    # holds the table to the routes), so on a known path the router's 405 with Allow is all
    # there is to reach, and it tells what OPTIONS tells; an unknown path needs ADMIN.
    return _options_role(path)
