"""The server's listening socket: its connections send small writes at once (TCP_NODELAY).

A response goes out in two writes (headers, body). With Nagle's algorithm on, the second waits for the
client's ACK of the first, which a client delays by 40 ms: every request took 44 ms. asyncio turns Nagle off
on accepted connections only when the listener was made with ``proto=IPPROTO_TCP``.
"""

from __future__ import annotations

import asyncio
import socket

from mapserver.api.lifecycle import bind_listener


async def _nodelay_of_accepted(listener: socket.socket) -> int:
    """Return TCP_NODELAY of the connection asyncio accepts on ``listener`` (a server on it, one client)."""
    seen: asyncio.Future[int] = asyncio.get_running_loop().create_future()

    class Probe(asyncio.Protocol):
        def connection_made(self, transport: asyncio.BaseTransport) -> None:
            sock = transport.get_extra_info("socket")
            seen.set_result(sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY))
            transport.close()

    server = await asyncio.get_running_loop().create_server(Probe, sock=listener)
    host, port = listener.getsockname()[:2]
    _, writer = await asyncio.open_connection(host, port)
    try:
        return await asyncio.wait_for(seen, 10)
    finally:
        writer.close()
        server.close()


def test_connections_of_the_servers_listener_have_nagle_off() -> None:
    listener = bind_listener("127.0.0.1", 0)
    assert listener.proto == socket.IPPROTO_TCP
    assert asyncio.run(_nodelay_of_accepted(listener)) != 0


def test_a_listener_made_without_the_protocol_keeps_nagle_on() -> None:
    # why bind_listener names the protocol: asyncio leaves such a listener's connections as they are
    plain = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    plain.bind(("127.0.0.1", 0))
    plain.listen(8)
    assert plain.proto == 0
    assert asyncio.run(_nodelay_of_accepted(plain)) == 0
