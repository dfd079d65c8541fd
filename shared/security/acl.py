"""Zenoh access control generated from `proto/streams.yaml`: default deny, rules per identity.

Each stream's `access` says which roles publish, subscribe, serve, query, hold a token or watch; an
identity's grants (`identities.parse_identity`) fill the stream's key placeholders with its bindings
(mec-agent1 -> `rmmdet/v1/agent1/objects`; unbound ones become `*`). A verb becomes the Zenoh messages
and flows it needs at the router, seen from the holder's face: a publisher's `put` is ingress, a
subscriber's deliveries are egress, and so on (`VERB_MESSAGES`).

Routers in a chain see each other, not the clients behind them: on the cloud router a site router's
subject holds the union of its site's identities' grants, on the site router the cloud router's subject
holds the union of the cloud side's. Each router enforces its own clients' rules, so a site can at most
do what its own identities may.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Mapping
from typing import Any

from shared.bus.streams import Stream, data_keys, readers, streams, wide_key
from shared.security.identities import ROLES, SERVICE_OF_ROLE, Grant, own_instance, parse_identity

#: (message, flow) pairs at the router for each access verb, from the holder's side.
VERB_MESSAGES: dict[str, tuple[tuple[str, str], ...]] = {
    "publish": (("put", "ingress"), ("delete", "ingress")),
    "subscribe": (("declare_subscriber", "ingress"), ("put", "egress"), ("delete", "egress")),
    "serve": (("declare_queryable", "ingress"), ("reply", "ingress")),
    "query": (("query", "ingress"), ("reply", "egress")),
    "token": (("liveliness_token", "ingress"),),
    "watch": (
        ("declare_liveliness_subscriber", "ingress"),
        ("liveliness_query", "ingress"),
        ("liveliness_token", "egress"),
        ("reply", "egress"),
    ),
}
#: What a holder must be told of others, on the stream's whole key space: Zenoh checks a declaration
#: or query against the allowed key expressions as a whole, and the interested party's may be wider
#: than the holder's own keys (the coordinator subscribes `*/objects`, the operator queries
#: `*/@health/**`). Knowing that someone listens reveals no data; the data itself stays confined.
VERB_INTEREST: dict[str, tuple[tuple[str, str], ...]] = {
    "publish": (("declare_subscriber", "egress"),),  # where to route its puts
    "serve": (("query", "egress"),),  # the queries it is to answer
    "query": (("declare_queryable", "egress"),),  # where to route its queries
}


#: A must-deliver stream rides Zenoh's advanced publisher/subscriber (`Stream.advanced`), whose publisher
#: holds a token and serves its cache under `<key>/@adv/...`: a stream verb brings these verbs on
#: that key space (`@adv` is a verbatim chunk: no `**` grant reaches it) ...
ADVANCED_VERBS: dict[str, tuple[str, ...]] = {
    "publish": ("token", "serve"),  # no puts of its own there: the publishers run without heartbeats
    "subscribe": ("subscribe", "watch", "query"),
}
#: ... and the cache's replies carry the samples' own keys: the publisher replies, the subscriber gets them.
ADVANCED_REPLIES: dict[str, tuple[str, str]] = {
    "publish": ("reply", "ingress"),
    "subscribe": ("reply", "egress"),
}


def role_matches(token: str, grant: Grant) -> bool:
    """`token` from streams.yaml (`role` or `role/kind`) covers `grant`."""
    role, _, kind = token.partition("/")
    if role not in ROLES:
        raise ValueError(f"streams.yaml names unknown role {role!r} (known: {ROLES})")
    return role == grant.role and (not kind or grant.bindings.get("kind") == kind)


#: Verbs on a node's own health and presence keys: their `service` chunk is the holder's own.
OWN_KEY_VERBS = ("serve", "token")
#: Bindings that confine only what the holder sends (publish, serve, token): a coordinator shard
#: publishes only its own region's maps and clique but reads every region's clique.
SENT_ONLY = ("region",)
SENDING_VERBS = ("publish", "serve", "token")


def key_for(stream: Stream, grant: Grant, verb: str) -> str:
    """The stream's key expression confined to the grant's bindings (`*` where it has none): an agent
    binding also fills `scope`; a node serves health and holds presence under its own service name and
    instance (`identities.own_instance`)."""
    own = verb in OWN_KEY_VERBS
    b = (
        grant.bindings
        if verb in SENDING_VERBS
        else {k: v for k, v in grant.bindings.items() if k not in SENT_ONLY}
    )
    fill = {
        "scope": b.get("scope", b.get("agent", "*")),
        "service": SERVICE_OF_ROLE.get(grant.role, "*") if own else "*",
        "instance": own_instance(grant) if own else "*",
    }
    ids = {f: b.get(f, fill.get(f, "*")) for f in stream.fields}
    return stream.key_template.format(**ids)


def grant_permissions(grants: Iterable[Grant]) -> dict[tuple[str, str], set[str]]:
    """(message, flow) -> key expressions the grants allow. A reader role (streams.yaml `readers`) may
    also subscribe to every pub/sub stream, each on its whole key space (`streams.data_keys`): never
    to `rmmdet/v1/**` at once, since every publisher would then have to be told of that subscription,
    and a grant that wide tells a vehicle of every other vehicle's plan subscription (its id)."""
    out: dict[tuple[str, str], set[str]] = defaultdict(set)
    grants = list(grants)
    if any(g.role in readers() for g in grants):
        for pair in VERB_MESSAGES["subscribe"]:
            out[pair].update(data_keys())
    for stream in streams().values():
        for verb, tokens in stream.access.items():
            for grant in grants:
                if any(role_matches(t, grant) for t in tokens):
                    for pair in VERB_MESSAGES[verb]:
                        out[pair].add(key_for(stream, grant, verb))
                    for pair in VERB_INTEREST.get(verb, ()):
                        out[pair].add(wide_key(stream))
                    if stream.advanced:
                        _grant_advanced(out, stream, key_for(stream, grant, verb), verb)
    return out


def _grant_advanced(out: dict[tuple[str, str], set[str]], stream: Stream, key: str, verb: str) -> None:
    # The cache is queried on `<key>/@adv/**` (history) and `<key>/@adv/pub/<zid>/<eid>/...` (recovery).
    own, anyone = f"{key}/@adv/**", f"{stream.pattern()}/@adv/**"
    if verb in ADVANCED_REPLIES:
        out[ADVANCED_REPLIES[verb]].add(key)
    for adv_verb in ADVANCED_VERBS.get(verb, ()):
        for pair in VERB_MESSAGES[adv_verb]:
            out[pair].add(own)
        for pair in VERB_INTEREST.get(adv_verb, ()):
            out[pair].add(anyone)


def identity_grants(names: Iterable[str]) -> list[Grant]:
    return sorted(
        {g for n in names for g in parse_identity(n).grants}, key=lambda g: (g.role, str(g.bindings))
    )


def access_control(
    subjects: dict[str, list[str]], common_names: Mapping[str, str] | None = None
) -> dict[str, Any]:
    """The router's `access_control` section: `subjects` maps each identity that may connect to the
    identities whose grants it holds (itself, or a whole site for a router); its certificate's common
    name is `common_names[identity]` (a revoked leaf's successor, `pki.revoke`), else the identity."""
    common_names = common_names or {}
    rules: list[dict[str, Any]] = []
    zsubjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for cn in sorted(subjects):
        perms = grant_permissions(identity_grants(subjects[cn]))
        by_keys: dict[tuple[str, tuple[str, ...]], list[str]] = defaultdict(list)
        for (message, flow), key_set in perms.items():
            by_keys[(flow, tuple(sorted(key_set)))].append(message)
        rule_ids = []
        for i, ((flow, keys), messages) in enumerate(sorted(by_keys.items())):
            rule_id = f"{cn}-{i}"
            rules.append(
                {
                    "id": rule_id,
                    "messages": sorted(messages),
                    "flows": [flow],
                    "permission": "allow",
                    "key_exprs": list(keys),
                }
            )
            rule_ids.append(rule_id)
        zsubjects.append({"id": cn, "cert_common_names": [common_names.get(cn, cn)]})
        if rule_ids:
            policies.append({"id": f"{cn}-policy", "rules": rule_ids, "subjects": [cn]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": zsubjects,
        "policies": policies,
    }
