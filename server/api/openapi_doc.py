"""The OpenAPI document: what FastAPI generates, made to say what the app really does.

FastAPI describes the routes, but two things it cannot see: the 422 body the
app's own validation handler sends (server/bootstrap/app.py, `_install_error_handlers`),
and the gate (server/api/access.py, `Access.check`), in a middleware, so the
generated document knows nothing of tokens, roles, 401 or 403. Both are
patched in here, in one place; the gate's part is derived from the same policy
table the gate reads (server/security/policy.py), so the document cannot drift
from what is enforced. openapi.json in the repository is this document
(`python -m server.cli.openapi --write`). Each operation's id is short
(`operation_id_of`, or the command catalogue's for a command).
"""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from fastapi.routing import APIRoute

from server.api.schemas import ErrorView
from server.commands.catalogue import STOP_PATHS
from server.security.policy import required_role
from server.security.tokens import Role

BEARER_SCHEME = "bearer"  # the name of the security scheme in openapi.json
_UNTRUSTED = "the client address is not in `trusted_networks`"
_HTTP_METHODS = {"get", "put", "post", "delete", "options", "head", "patch", "trace"}


def operation_id_of(route: APIRoute) -> str:
    """A route's OpenAPI operationId: its function's name in camelCase (`get_state` →
    `getState`), short and stable while the function keeps its name. The command
    routes set theirs from the command catalogue instead (server/commands/catalogue.py);
    tests/integration/test_api_schema.py checks that every id is unique."""
    head, *rest = route.name.split("_")
    return head + "".join(part[:1].upper() + part[1:] for part in rest)


def install(app: FastAPI) -> None:
    """Serve the app's document with its validation errors and its gate described.

    Built once, on first use, like FastAPI's own.
    """
    default_openapi = app.openapi

    def openapi() -> dict:
        if app.openapi_schema is None:
            schema = default_openapi()
            document_validation_errors(schema)
            document_access(schema)
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


def document_validation_errors(schema: dict[str, Any]) -> None:
    """Describe the 422 body this app really sends, and the 400 of an unreadable body."""
    schema["components"]["schemas"]["HTTPValidationError"] = {
        "title": "HTTPValidationError",
        "type": "object",
        "required": ["detail"],
        "properties": {
            "detail": {"type": "string", "description": "every problem, one line"},
            "errors": {
                "type": "array",
                "items": {
                    "type": "object",
                    "required": ["field", "message", "type"],
                    "properties": {
                        "field": {"type": "string"},
                        "message": {"type": "string"},
                        "type": {"type": "string"},
                    },
                },
            },
        },
    }
    schema["components"]["schemas"].pop("ValidationError", None)
    # A body that is not even text (invalid UTF-8) is refused by the framework
    # with 400 before validation; say so on every operation that takes a body.
    for path in schema["paths"].values():
        for operation in path.values():
            if "requestBody" in operation:
                operation["responses"].setdefault(
                    "400",
                    {
                        "description": "the body could not be read (not UTF-8 JSON)",
                        "content": {
                            "application/json": {
                                "schema": {"$ref": "#/components/schemas/ErrorView"}
                            }
                        },
                    },
                )


def _refusal(description: str, **extra: Any) -> dict[str, Any]:
    """A documented 401 or 403: the `{"detail": ...}` body of FastAPI's HTTPException handler."""
    body = {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorView"}}}
    return {"description": description, **extra, "content": body}


def document_access(schema: dict[str, Any]) -> None:
    """Describe the access gate in an OpenAPI document: the bearer scheme, who may call what,
    401/403.

    Derived from the policy table, as `Access.check` is: an operation that needs a role gets the
    security requirement, `x-required-role`, a sentence in its description and the 401 and 403
    it can answer; an open one gets only the 403 of `trusted_networks`, which applies to all.
    """
    components = schema.setdefault("components", {})
    components.setdefault("schemas", {}).setdefault("ErrorView", ErrorView.model_json_schema())
    components["securitySchemes"] = {
        BEARER_SCHEME: {
            "type": "http",
            "scheme": "bearer",
            "bearerFormat": "gc_<id>_<secret>",
            "description": "A token from `POST /tokens` or `<data>/admin.token`, sent as "
            "`Authorization: Bearer <token>`; each operation's `x-required-role` is the "
            "least role it needs (viewer < operator < maintenance < admin).",
        }
    }
    for path, operations in schema.get("paths", {}).items():
        for method, operation in operations.items():
            if method not in _HTTP_METHODS:
                continue
            needed = required_role(method.upper(), path)
            responses = operation.setdefault("responses", {})
            if needed is None:
                responses["403"] = _refusal(_UNTRUSTED)
                continue
            operation["security"] = [{BEARER_SCHEME: []}]
            operation["x-required-role"] = needed.label
            who = {
                Role.VIEWER: "any valid bearer token (every role)",
                Role.ADMIN: "a bearer token with the `admin` role",
            }.get(needed, f"a bearer token with the `{needed.label}` role or higher")
            operation["description"] = (
                f"{operation.get('description', '').rstrip()}\n\nNeeds {who}.".lstrip()
            )
            responses["401"] = _refusal(
                "no bearer token, or the token is unknown or revoked",
                headers={
                    "WWW-Authenticate": {
                        "description": "the scheme to authenticate with",
                        "required": True,
                        "schema": {"type": "string", "enum": ["Bearer"]},
                    }
                },
            )
            if not (method == "post" and path in STOP_PATHS):  # the e-stop never waits
                responses["429"] = _refusal(
                    "this client's address sent `auth_failure_limit` bad tokens within "
                    "`auth_failure_window`: refused, whatever the token, until `Retry-After`",
                    headers={
                        "Retry-After": {
                            "description": "seconds until the address may try again",
                            "required": True,
                            "schema": {"type": "integer", "minimum": 1},
                        }
                    },
                )
            responses["403"] = _refusal(
                _UNTRUSTED
                if needed == Role.VIEWER  # no role is below it
                else f"the token's role is below `{needed.label}` (the detail names the role "
                f"needed and the role held), or {_UNTRUSTED}"
            )
