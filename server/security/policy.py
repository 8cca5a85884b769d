"""The access policy: which role each route needs, declared once.

`None` means open to anyone (the health check and the API description).
A route missing from the table needs ADMIN: new routes are closed until
someone decides otherwise. The software stop is open to every authenticated
principal, whatever its role: nobody must be unable to stop the cell.
"""

from __future__ import annotations

from types import MappingProxyType
from typing import Final

from server.security.tokens import Role

VIEW, OPER, MAINT, ADMIN = Role.VIEWER, Role.OPERATOR, Role.MAINTENANCE, Role.ADMIN

POLICY: Final = MappingProxyType(
    {
        # open
        ("GET", "/health"): None,
        ("GET", "/"): None,  # the operator dashboard's page (it asks for a token itself)
        ("GET", "/openapi.json"): None,
        ("GET", "/docs"): None,
        ("GET", "/docs/oauth2-redirect"): None,
        ("GET", "/redoc"): None,
        # viewer: look, and stop
        ("GET", "/state"): VIEW,
        ("GET", "/operations/{name}/allowed"): VIEW,
        ("GET", "/history"): VIEW,
        ("GET", "/operations"): VIEW,
        ("GET", "/errors"): VIEW,
        ("GET", "/events"): VIEW,
        ("GET", "/export/{table}.csv"): VIEW,
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


def required_role(method: str, path: str) -> Role | None:
    """The role a route needs (None: open); unknown routes need ADMIN."""
    method = "GET" if method == "HEAD" else method
    return POLICY.get((method, path), Role.ADMIN)
