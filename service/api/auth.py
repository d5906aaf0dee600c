"""Who may do what: API keys from settings (``auth.keys``), each with a role.

``read`` may align and list; ``admin`` may also register and delete. A key is sent as
``Authorization: Bearer <key>`` or ``X-API-Key: <key>``. Once any key is configured, writes
need an admin key, and reads need a key unless ``auth.require_key_for_reads`` is off. With no
key configured the service is open, and says so in its log and in ``/health``. The probes,
``/health`` and ``/metrics`` stay open. Keys are compared in constant time and never logged.

The routes declare ``ReadAccess`` or ``AdminAccess`` as dependencies; the role travels as the
security scope, so the OpenAPI document says which role each operation needs.
"""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, HTTPException, Security
from fastapi.security import (
    APIKeyHeader,
    HTTPAuthorizationCredentials,
    HTTPBearer,
    SecurityScopes,
)

from service.api.dependencies import SettingsDep
from service.settings import AuthSettings, Role

RANK: dict[str, int] = {"read": 1, "admin": 2}
CHALLENGE = {"WWW-Authenticate": "Bearer"}
HOW = "send it as 'Authorization: Bearer <key>' or 'X-API-Key: <key>'"

bearer = HTTPBearer(auto_error=False, description="an API key as `Authorization: Bearer <key>`")
api_key = APIKeyHeader(name="X-API-Key", auto_error=False, description="an API key")


def mode(auth: AuthSettings) -> str:
    """What ``/health`` reports: ``open``, ``keys`` or ``keys-for-writes``."""
    if not auth.keys:
        return "open"
    return "keys" if auth.require_key_for_reads else "keys-for-writes"


def role_of(presented: str, keys: dict[str, Role]) -> Role | None:
    """The role of a presented key, or None; every key is compared, each in constant time."""
    candidate = presented.encode()
    found = None
    for key, role in keys.items():
        if hmac.compare_digest(candidate, key.encode()):
            found = role
    return found


async def authorize(
    scopes: SecurityScopes,
    settings: SettingsDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
    header_key: Annotated[str | None, Depends(api_key)],
) -> Role | None:
    """The caller's role, if the operation's role (the scope) needs a key; else 401 or 403."""
    (needed,) = scopes.scopes
    auth = settings.auth
    if not auth.keys or (needed == "read" and not auth.require_key_for_reads):
        return None
    presented = credentials.credentials if credentials else header_key
    if not presented:
        raise HTTPException(401, f"this operation needs an API key: {HOW}", headers=CHALLENGE)
    role = role_of(presented, auth.keys)
    if role is None:
        raise HTTPException(401, f"the API key is not valid: {HOW}", headers=CHALLENGE)
    if RANK[role] < RANK[needed]:
        raise HTTPException(403, f"this key has the '{role}' role; this operation needs '{needed}'")
    return role


ReadAccess = Security(authorize, scopes=["read"])
AdminAccess = Security(authorize, scopes=["admin"])
