"""The one way a scan is answered: a pose or an error on its vehicle's keys, counted."""

from __future__ import annotations

import logging
from collections.abc import Callable

from randt.service.metrics import ServiceMetrics
from randt.wire.ids import UNKNOWN_ID
from randt.wire.messages import ErrorMessage, WireLimits, WireMessage

__all__ = ["Answers", "Outbox"]

log = logging.getLogger(__name__)

#: Where results go: the transport (Zenoh) or, in tests, a list. Must not block for long.
Outbox = Callable[[WireMessage], None]


class Answers:
    """Errors and messages to the outbox, counted in the service's metrics."""

    def __init__(self, outbox: Outbox, metrics: ServiceMetrics, limits: WireLimits) -> None:
        self.outbox = outbox
        self.metrics = metrics
        self.limits = limits

    def error(
        self,
        vehicle: str,
        session: str,
        seq: int | None,
        code: str,
        reason: str,
        retry_after_s: float | None = None,
        *,
        count: bool = True,
    ) -> str | None:
        """Answer one scan with an error (``code``: an :class:`~randt.wire.codes.ErrorCode`; a
        refusal that passes says when to send again, ``retry_after_s``) on its vehicle's error key
        and count it. Returns the session id it was answered on (``None``: no key to answer on)."""
        if count:
            self.metrics.scans_rejected.labels(code).inc()
        if not self.limits.id_ok(vehicle):
            # No valid key to answer on (randt/fleet/<vehicle>/error): counted and logged only.
            log.warning(
                "rejected a scan from an unaddressable vehicle id %r: %s: %s", vehicle[:40], code, reason
            )
            return None
        if not self.limits.id_ok(session):
            session = UNKNOWN_ID
        self.outbox(
            ErrorMessage(
                vehicle=vehicle,
                session=session,
                seq=seq,
                code=code,
                reason=reason,
                retry_after_s=retry_after_s,
            )
        )
        return session

    def send(self, message: WireMessage) -> None:
        self.outbox(message)
