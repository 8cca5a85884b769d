"""The access policy: which role each route needs, declared once.

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

from server.security.tokens import Role

VIEW, OPER, MAINT, ADMIN = Role.VIEWER, Role.OPERATOR, Role.MAINTENANCE, Role.ADMIN

POLICY: Final = MappingProxyType(
    {
        # open
        ("GET", "/health"): None,
        ("GET", "/"): None,  # the operator dashboard's page (it asks for a token itself)
        # viewer: look, and stop
        ("GET", "/openapi.json"): VIEW,  # also in the repository, for integrators
        ("GET", "/state"): VIEW,
        ("GET", "/operations/{name}/allowed"): VIEW,
        ("GET", "/history"): VIEW,
        ("GET", "/operations"): VIEW,
        ("GET", "/errors"): VIEW,
        ("GET", "/events"): VIEW,
        # one CSV route per journal table, each with that table's own filters
        ("GET", "/export/events.csv"): VIEW,
        ("GET", "/export/transitions.csv"): VIEW,
        ("GET", "/export/operations.csv"): VIEW,
        ("GET", "/export/errors.csv"): VIEW,
        ("GET", "/export/recoveries.csv"): VIEW,
        ("GET", "/kpis"): VIEW,
        ("GET", "/metrics"): VIEW,
        ("GET", "/calibration"): VIEW,
        ("GET", "/calibration/image"): VIEW,
        ("GET", "/camera/frame"): VIEW,
        ("GET", "/trajectory"): VIEW,
        ("GET", "/workpieces"): VIEW,
        ("GET", "/workpieces/{workpiece_id}"): VIEW,
        ("GET", "/workpieces/{workpiece_id}/thumbnail"): VIEW,
        ("POST", "/ws-ticket"): VIEW,
        ("POST", "/estop"): VIEW,
        # operator: run production
        ("POST", "/start"): OPER,
        ("POST", "/pause"): OPER,
        ("POST", "/resume"): OPER,
        ("POST", "/cancel"): OPER,
        ("POST", "/create-workpiece"): OPER,
        # maintenance: calibrate, recover, edit the library
        ("POST", "/calibrate-robot"): MAINT,
        ("POST", "/calibrate-camera"): MAINT,
        ("POST", "/reset"): MAINT,
        ("POST", "/home"): MAINT,
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
    }
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


def role_for_request(method: str, path: str) -> Role | None:
    """The role a request needs, from its concrete path (None: open).

    The gate checks before routing, so it matches the path itself: exact paths
    by lookup, templated ones by their regex. A path no entry matches needs
    ADMIN (the app then answers 404 or 405): new routes stay closed until the
    table names them.
    """
    method = "GET" if method == "HEAD" else method
    if (method, path) in _EXACT:
        return _EXACT[(method, path)]
    for entry_method, pattern, templated_role in _TEMPLATED:
        if entry_method == method and pattern.match(path):
            return templated_role
    if method == "GET" and path.startswith(OPEN_PREFIXES):
        return None
    return Role.ADMIN
