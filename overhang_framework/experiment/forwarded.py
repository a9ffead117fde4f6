"""The server behind a reverse proxy: the address the participant opened, from the proxy's headers.

A proxy (nginx, docs/deploy.md) passes each request on with ``X-Forwarded-Proto``
(``https``), ``X-Forwarded-For`` (the participant's address) and
``X-Forwarded-Host`` (the host and port the participant opened). From a proxy
that ``forwarded_allow_ips`` names, :class:`ForwardedHeaders` makes the request
look as it did to the participant: uvicorn's proxy-headers middleware sets the
scheme and the client, and the ``Host`` header becomes ``X-Forwarded-Host``.
From anyone else the headers are ignored, so a participant cannot make the
server write links to another site.
"""

from __future__ import annotations

import re

from uvicorn.middleware.proxy_headers import ProxyHeadersMiddleware

#: A host, optionally with a port: what may replace the ``Host`` header.
HOST = re.compile(rb"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]+)(:[0-9]{1,5})?$")


class ForwardedHeaders:
    """ASGI middleware: requests from ``trusted`` proxies (uvicorn's ``forwarded_allow_ips`` syntax) get the
    scheme, client and host their ``X-Forwarded-*`` headers name."""

    def __init__(self, app, trusted: str = "127.0.0.1"):
        self.app = ProxyHeadersMiddleware(app, trusted_hosts=trusted)
        self.trusted = self.app.trusted_hosts

    async def __call__(self, scope, receive, send):
        if scope["type"] in ("http", "websocket"):
            client = scope.get("client")
            if client and client[0] in self.trusted:
                scope = _with_forwarded_host(scope)
        await self.app(scope, receive, send)


def _with_forwarded_host(scope):
    values = [v for name, v in scope["headers"] if name == b"x-forwarded-host"]
    if not values:
        return scope
    host = values[-1].split(b",")[-1].strip()  # the value the nearest proxy (a trusted one) set
    if not HOST.match(host):
        return scope
    headers = [(name, v) for name, v in scope["headers"] if name != b"host"] + [(b"host", host)]
    return {**scope, "headers": headers}
