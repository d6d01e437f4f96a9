"""What travels beside a work item and a receipt (Zenoh attachments): the item's age and deadline,
its nonce and, for a pool worker, the grant it uses."""
from __future__ import annotations

import msgpack

from common.errors import DecodeError


def make_attachment(age_ms: float, max_age_ms: float, nonce: bytes = b"", grant: str = "") -> bytes:
    """Sent beside the (unchanged) StereoFrame payload: its age when sent and the max age, so a
    worker on another host can tell its age without synchronised clocks, and the item's random
    nonce, which the worker's answer must carry back (results.py); to a pool worker, also the grant
    it was sent against (fleet.py)."""
    doc = {"age_ms": float(age_ms), "max_age_ms": float(max_age_ms), "nonce": nonce}
    if grant:
        doc["grant"] = grant
    return msgpack.packb(doc, use_bin_type=True)


def parse_attachment(raw: bytes | None) -> tuple[float, float, bytes]:
    """-> (age_ms when sent, max_age_ms, nonce); (0, inf, b"") without one. Garbage raises DecodeError."""
    if raw is None:
        return 0.0, float("inf"), b""
    try:
        doc = msgpack.unpackb(raw)
        nonce = doc.get("nonce", b"")
        if not isinstance(nonce, bytes) or len(nonce) > 64:
            raise ValueError(f"nonce: {len(nonce) if isinstance(nonce, bytes) else type(nonce).__name__}")
        return float(doc["age_ms"]), float(doc["max_age_ms"]), nonce
    except Exception as e:
        raise DecodeError(f"work item attachment: {type(e).__name__}: {e}") from None


def receipt_attachment(nonce: bytes) -> bytes:
    """A receipt's attachment: the nonce of the item it is about (no nonce, no effect)."""
    return msgpack.packb({"nonce": nonce}, use_bin_type=True)


def receipt_nonce(raw: bytes | None) -> bytes:
    try:
        doc = msgpack.unpackb(raw) if raw is not None and len(raw) <= 256 else None
        nonce = doc.get("nonce") if isinstance(doc, dict) else None
        return nonce if isinstance(nonce, bytes) else b""
    except Exception:
        return b""


def _attachment_bytes(sample) -> bytes | None:
    try:
        return sample.attachment.to_bytes() if sample.attachment is not None else None
    except Exception:
        return None


