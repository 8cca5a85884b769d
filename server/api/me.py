"""GET /me: who is signed in, and what their token may do, for a page to draw itself.

A page offers only what its user may do: the command buttons of the token's role, the
Set-up link only for a role that may open the camera's set-up view, and, when the cell
waits for a command the role lacks (a reset after a stop needs maintenance), words
saying whom to call. All of it is read from the command catalogue
(server/commands/catalogue.py) and the access policy (server/security/policy.py), the
places that decide; the page only draws it. The state's own `available_commands`
(GET /state, /ws) then says which of those the cell accepts now.
"""

from __future__ import annotations

from fastapi import APIRouter, Request
from pydantic import BaseModel, Field

from server.api.declared_query import DeclaredQueryRoute
from server.commands.catalogue import CATALOGUE, may, may_send
from server.security.policy import required_role
from server.security.tokens import Principal, Role

router = APIRouter(tags=["queries"], route_class=DeclaredQueryRoute)

# The pages a role may open, by the route each needs first.
PAGES = {"setup": ("GET", "/camera/preview")}


class CommandRole(BaseModel):
    """One command of the catalogue, as it concerns the caller."""

    name: str
    role: str = Field(description="the least role that may send it")
    allowed: bool = Field(description="whether the caller's role may send it (its state aside)")


class MeView(BaseModel):
    """GET /me."""

    name: str = Field(description="the token's name, as the audit and stop reasons show it")
    role: str = Field(description="viewer, operator, maintenance or admin")
    commands: list[CommandRole] = Field(description="every command, with the role it needs")
    may: list[str] = Field(
        description="the commands the current state allows that the role allows too"
    )
    pages: dict[str, bool] = Field(description="the pages the role may open (setup)")


def describe(principal: Principal, available: list[str]) -> MeView:
    """What GET /me answers for `principal`, the cell allowing `available` now (pure)."""
    return MeView(
        name=principal.name,
        role=principal.role.label,
        commands=[
            CommandRole(
                name=spec.name,
                role=spec.role.label,
                allowed=may_send(principal.role, spec.command),
            )
            for spec in CATALOGUE
        ],
        may=may(principal.role, available),
        pages={
            page: principal.role >= (required_role(method, path) or Role.VIEWER)
            for page, (method, path) in PAGES.items()
        },
    )


@router.get("/me", response_model=MeView)
async def get_me(request: Request) -> MeView:
    """The signed-in token's name and role, each command's role, what it may do now."""
    principal: Principal = request.state.principal
    available = request.app.state.cell.view.snapshot()["available_commands"]
    return describe(principal, available)
