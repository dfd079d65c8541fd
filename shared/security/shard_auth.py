"""What a coordinator shard signs and checks of what the others tell it (issue 52 items 1-3).

Every shard signs with its own plan key (`pki.shard_plan_key_name`) and trusts the others' public keys,
the vehicles' set (`pki.trusted_plan_keys`). Three messages travel between shards:

    clique           signed with the stamp it is published with (its age is that stamp's): taken for
                     region k only when shard k's key signed it
    release request  signed with its header stamp: the region it claims is the signer's, and the
                     stamp within the bus's clock skew of the receiver's wall clock (a replay is old)
    handover         the releasing shard's answer, signed with the request's stamp: an answer to that
                     request, from some other shard's key

Zenoh's access control binds the clique's key to the shard's certificate on the multi-site profile but
cannot bind a field inside a payload (the region a release claims) and is absent on one host; the
signatures hold on every profile. `problem` names a refusal as a counter suffix.
"""

from __future__ import annotations

from google.protobuf.message import Message

from shared.security.pki import shard_plan_key_name
from shared.security.plan_signing import M, PlanSigner, PlanVerifier
from shared.timebase import NS_PER_S


class ShardAuth:
    """Shard `region`'s signer and its verifier of every shard's key; `max_skew_s` bounds the age of a
    release request (the bus's clock skew between hosts)."""

    def __init__(self, region: int, signer: PlanSigner, verifier: PlanVerifier, max_skew_s: float) -> None:
        self.region, self.signer, self.verifier = region, signer, verifier
        self.max_skew_ns = round(max_skew_s * NS_PER_S)
        self.own = shard_plan_key_name(region)

    def sign(self, message: M, stamp_ns: int) -> M:
        return self.signer.sign(message, stamp_ns)

    def problem(self, message: Message, stamp_ns: int, region: int | None) -> str | None:
        """Why `message` (travelling with `stamp_ns`) is not shard `region`'s (None: any shard's but
        this one's): `unsigned`, `unknown_key`, `bad_signature`, `wrong_shard`; None when it is."""
        problem = self.verifier.problem(message, stamp_ns)
        if problem is not None:
            return problem
        signer = self.verifier.signer(message)
        if region is not None:
            return None if signer == shard_plan_key_name(region) else "wrong_shard"
        shards = signer is not None and signer.startswith(shard_plan_key_name(0).removesuffix("0"))
        return None if shards and signer != self.own else "wrong_shard"

    def request_problem(self, message: Message, stamp_ns: int, region: int, now_ns: int) -> str | None:
        """`problem` for a request claiming to come from `region`, and `stale` when its stamp is further
        than the clock skew from `now_ns` (wall)."""
        if abs(now_ns - stamp_ns) > self.max_skew_ns:
            return "stale"
        return self.problem(message, stamp_ns, region)
