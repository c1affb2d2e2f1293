"""A session's track: whether a scan's pose may be answered, or the session is lost until it
matches again (``docs/clients.md``: what a vehicle sees)."""

from __future__ import annotations

import logging

from randt.core.odometry import RELOCALIZED, ScanResult
from randt.service.session_info import SessionInfo
from randt.wire.messages import ScanHeader

__all__ = ["VERIFY_MATCHES", "track"]

log = logging.getLogger(__name__)

#: A lost session answers poses again after this many consecutive matches.
VERIFY_MATCHES = 2


def track(info: SessionInfo, scan: ScanHeader, result: ScanResult, horizon_s: float) -> str | None:
    """Whether the scan's pose may be answered (``None``) or why the session is lost.

    A fallback's pose is the motion prediction, right only over a short gap: it is answered
    while the last match is at most ``fallback_horizon_s`` old (scan stamps). Past that the
    session is lost: no pose, nothing folded or offered to the graph, until
    :data:`VERIFY_MATCHES` consecutive scans match (two agreeing registrations). A match the
    matcher found by relocalization (:data:`RELOCALIZED`) is the first of those, never
    answered by itself: a place that merely looks alike can be tens of metres off."""
    key, horizon = (info.vehicle, info.session), horizon_s
    if result.status == "ok" and result.message == RELOCALIZED and not info.lost:
        log.warning("session %s/%s relocalized at scan %d: to be verified", *key, scan.seq)
        info.lost, info.verified_matches = True, 0
    if result.status == "fallback":
        info.verified_matches = 0
        since_ns = None if info.matched_stamp_ns is None else scan.stamp_ns - info.matched_stamp_ns
        if not info.lost and since_ns is not None and since_ns <= horizon * 1e9:
            return None
        if not info.lost:
            log.warning("session %s/%s lost its track at scan %d", *key, scan.seq)
        info.lost = True
        began = "since it began" if info.n_scans == 0 else "since it resumed"
        gap = began if since_ns is None else f"for {since_ns * 1e-9:.2f} s"
        return (
            f"lost: no match {gap} (a prediction is answered for {horizon:g} s at most); "
            f"poses resume after {VERIFY_MATCHES} consecutive matches"
        )
    info.matched_stamp_ns = scan.stamp_ns
    if not info.lost:
        return None
    info.verified_matches += 1
    if info.verified_matches < VERIFY_MATCHES:
        why = f"lost: relocalizing, {info.verified_matches} of {VERIFY_MATCHES} consecutive matches"
        return why
    log.info("session %s/%s found its track again at scan %d", *key, scan.seq)
    info.lost, info.verified_matches = False, 0
    return None
