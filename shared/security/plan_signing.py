"""Ed25519 signatures on route plans: the coordinator signs, vehicles verify.

Zenoh's access control keeps other identities from publishing on the plan keys, but it gives the
receiver no authenticated sender, and a second queryable on the route RPC key can answer a vehicle's
request (docs/reliability.md (c).12). So every plan carries a signature by the coordinator's plan key, over
the plan serialised deterministically with `header` and `signature` cleared (the header is rewritten by
the transport layer; everything a vehicle acts on is signed: vehicle, plan id, version, lanes, TTL).
`key_id` names the key, so keys can be rotated by trusting two at once.

A sharded coordinator's shards each sign with their own key (`pki.shard_plan_key_name`), and sign what
they tell each other too (cliques, release requests, handovers: any message with `key_id` and
`signature` fields, its header's stamp covered where the receiver judges freshness by it). A verifier
knows which signer each trusted key is (`signer`: the key file's name), so a vehicle can take a pushed
plan only from the shard that answered it, and a shard a clique of region k only from shard k.

Deterministic serialisation is stable for one protobuf runtime, which both ends share here (a
cross-language deployment would sign the exact bytes in an envelope instead).
"""

from __future__ import annotations

import hashlib
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey
from google.protobuf.message import Message

from shared.config import ConfigError
from shared.security.pki import PLAN_KEY_NAME, signer_name

M = TypeVar("M", bound=Message)

#: Length of an Ed25519 signature, bytes.
log = logging.getLogger(__name__)

SIGNATURE_BYTES = 64


def key_id(public_key: Ed25519PublicKey) -> str:
    """First 16 hex digits of the SHA-256 of the raw public key."""
    raw = public_key.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    return hashlib.sha256(raw).hexdigest()[:16]


def signed_bytes(message: Message, stamp_ns: int | None = None) -> bytes:
    """What the signature covers: the message without its header and signature, deterministically,
    followed by `stamp_ns` (8 bytes big-endian) where given: the stamp it travels with, when the
    receiver judges its age by it (a clique's; a plan carries its own times in its body)."""
    body = type(message)()
    body.CopyFrom(message)
    body.ClearField("header")
    body.ClearField("signature")
    out = body.SerializeToString(deterministic=True)
    if stamp_ns is not None:
        out += (stamp_ns & (2**64 - 1)).to_bytes(8, "big")
    return out


def load_private_key(path: Path) -> Ed25519PrivateKey:
    try:
        key = serialization.load_pem_private_key(path.read_bytes(), password=None)
    except FileNotFoundError:
        raise ConfigError(f"{path}: plan-signing key not found (create it with `rmmdet pki init`)") from None
    except ValueError as err:
        raise ConfigError(f"{path}: not a PEM private key: {err}") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise ConfigError(f"{path}: plan-signing key must be Ed25519, got {type(key).__name__}")
    return key


def load_public_key(path: Path) -> Ed25519PublicKey:
    try:
        key = serialization.load_pem_public_key(path.read_bytes())
    except FileNotFoundError:
        raise ConfigError(
            f"{path}: plan verification key not found (create it with `rmmdet pki init`)"
        ) from None
    except ValueError as err:
        raise ConfigError(f"{path}: not a PEM public key: {err}") from None
    if not isinstance(key, Ed25519PublicKey):
        raise ConfigError(f"{path}: plan verification key must be Ed25519, got {type(key).__name__}")
    return key


class PlanSigner:
    """The coordinator's side: `sign` sets `key_id` and `signature` in place (of a plan, or of any
    message with those fields; `stamp_ns`: the stamp it travels with, covered too)."""

    def __init__(self, private_key: Ed25519PrivateKey) -> None:
        self._key = private_key
        self.key_id = key_id(private_key.public_key())

    @classmethod
    def load(cls, path: Path) -> PlanSigner:
        return cls(load_private_key(path))

    def sign(self, message: M, stamp_ns: int | None = None) -> M:
        message.key_id = self.key_id  # type: ignore[attr-defined]
        message.signature = self._key.sign(signed_bytes(message, stamp_ns))  # type: ignore[attr-defined]
        return message


#: How often a watching verifier looks whether its key files changed (a rotation's stage or promotion).
KEY_RECHECK_S = 2.0


class PlanVerifier:
    """The vehicles' side: `problem` names why a plan's signature is not acceptable (None: it is).

    `watching` verifiers follow their key files: a key staged, promoted or retired by `rmmdet pki
    rotate --plan-key` is trusted or no longer trusted within KEY_RECHECK_S, no restart needed (a
    vehicle trusted a retired key until it restarted). A file that does not read keeps the keys held."""

    def __init__(
        self,
        public_keys: list[Ed25519PublicKey],
        source: Callable[[], list[Path]] | None = None,
        recheck_s: float = KEY_RECHECK_S,
        signers: list[str] | None = None,
    ) -> None:
        if not public_keys:
            raise ValueError("at least one trusted plan key")
        self._keys = _by_id(public_keys, signers)
        self._source, self._recheck_s = source, recheck_s
        self._files = _files_stamp(source()) if source is not None else ()
        self._due_s = time.monotonic() + recheck_s
        self._lock = threading.Lock()

    @classmethod
    def load(cls, paths: list[Path]) -> PlanVerifier:
        return cls([load_public_key(p) for p in paths], signers=[signer_name(p) for p in paths])

    @classmethod
    def watching(cls, source: Callable[[], list[Path]], recheck_s: float = KEY_RECHECK_S) -> PlanVerifier:
        """A verifier of the keys `source` lists (read now: ConfigError as `load`), re-read on a change."""
        paths = source()
        return cls([load_public_key(p) for p in paths], source, recheck_s, [signer_name(p) for p in paths])

    def _refresh(self) -> None:
        if self._source is None or time.monotonic() < self._due_s:
            return
        with self._lock:
            if time.monotonic() < self._due_s:
                return
            self._due_s = time.monotonic() + self._recheck_s
            paths = [p for p in self._source() if p.exists()]
            files = _files_stamp(paths)
            if files == self._files:
                return
            try:
                keys = [load_public_key(p) for p in paths]
            except ConfigError as err:  # mid-write, or damaged: keep what is trusted now
                log.warning("plan keys not reloaded: %s", err)
                return
            if not keys:
                return
            self._keys, self._files = _by_id(keys, [signer_name(p) for p in paths]), files
            log.info("trusted plan keys now: %s", ", ".join(sorted(self._keys)))

    def problem(self, message: Message, stamp_ns: int | None = None) -> str | None:
        """ "unsigned", "unknown_key" or "bad_signature"; None for a plan (or other signed message, see
        `PlanSigner.sign`) signed by a trusted key."""
        self._refresh()
        signature, kid = message.signature, message.key_id  # type: ignore[attr-defined]
        if not signature:
            return "unsigned"
        held = self._keys.get(kid)
        if held is None:
            return "unknown_key"
        try:
            held[0].verify(signature, signed_bytes(message, stamp_ns))
        except InvalidSignature:
            return "bad_signature"
        return None

    def signer(self, message: Message) -> str | None:
        """Which signer's key `message` names (`pki.signer_name`: `plan-signing` for the coordinator,
        `plan-signing.region<k>` for shard k), None for a key not trusted. Check `problem` first."""
        held = self._keys.get(message.key_id)  # type: ignore[attr-defined]
        return held[1] if held is not None else None


def _by_id(
    keys: list[Ed25519PublicKey], signers: list[str] | None
) -> dict[str, tuple[Ed25519PublicKey, str]]:
    names = signers if signers is not None else [PLAN_KEY_NAME] * len(keys)
    return {key_id(k): (k, name) for k, name in zip(keys, names, strict=True)}


def _files_stamp(paths: list[Path]) -> tuple[tuple[str, int, int], ...]:
    """Which key files there are and their versions (modification time, size): a change to look at."""
    out = []
    for p in paths:
        try:
            st = p.stat()
        except OSError:
            continue
        out.append((str(p), st.st_mtime_ns, st.st_size))
    return tuple(out)
