"""A deadline for receiving a request's headers (uvicorn has none: its keep-alive timeout restarts on every
byte, so a client sending headers one byte a second holds a connection for ever; ASGI middleware runs only
once the headers are in)."""

from __future__ import annotations

from uvicorn.protocols.http.h11_impl import H11Protocol


def with_header_deadline(seconds: float) -> type:
    """uvicorn's h11 protocol that closes a connection whose next request's headers are not complete within
    ``seconds`` of the connection opening or of the previous response ending (pass as ``uvicorn.run(http=...)``)."""

    class HeaderDeadline(H11Protocol):
        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            self._arm()

        def _arm(self) -> None:
            self._seen = self.cycle  # a request whose headers are in makes a new cycle
            self._deadline = self.loop.call_later(seconds, self._expire)

        def _disarm(self) -> None:
            timer, self._deadline = getattr(self, "_deadline", None), None
            if timer is not None:
                timer.cancel()

        def data_received(self, data: bytes) -> None:
            super().data_received(data)
            if getattr(self, "_deadline", None) is not None and self.cycle is not self._seen:
                self._disarm()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if not self.transport.is_closing():
                self._disarm()
                self._arm()

        def connection_lost(self, exc) -> None:
            self._disarm()
            super().connection_lost(exc)

        def _expire(self) -> None:
            self._deadline = None
            if self.cycle is self._seen and not self.transport.is_closing():
                self.transport.close()

    return HeaderDeadline
