"""The key space loaded from proto/streams.yaml: key builders, message types and QoS per stream.

>>> get_stream("objects").key(agent="agent1")
'rmmdet/v1/agent1/objects'
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import importlib
import re
import string
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import yaml
import zenoh
from google.protobuf.message import Message

from shared.bus import names
from shared.paths import REPO_ROOT

STREAMS_YAML = REPO_ROOT / "proto" / "streams.yaml"

#: One key chunk of an id (agent, sensor, vehicle, service, instance). No Zenoh-reserved characters.
#: Stream of each sensor kind's raw data (keys `.../<agent>/sensor/<kind>/<sensor>`).
SENSOR_STREAM = {"camera": "camera_image", "lidar": "point_cloud", "radar": "radar_scan"}
ID_PATTERN = re.compile(r"^[a-z0-9][a-z0-9_\-]{0,63}$")


def sensor_group(agent: str, kind: str) -> str:
    """Instance id of the sensor service that renders `agent`'s sensors of `kind` (`agent1-cameras`)."""
    return f"{agent}-{kind}s"


_SHARD_INSTANCE = re.compile(r"region(\d+)")


def shard_instance(region: int | str) -> str:
    """Instance id of the coordinator shard serving `region` (services/coordinator/shard.py)."""
    return f"region{region}"


def region_of_instance(instance: str) -> int | None:
    """The region of a coordinator shard's instance id; None for any other instance."""
    m = _SHARD_INSTANCE.fullmatch(instance)
    return int(m.group(1)) if m else None


def sensor_group_source(agent: str, kind: str) -> str:
    """Source id (`scope/service/instance`, as in its presence token) of that sensor service."""
    return f"{agent}/{names.SENSOR}/{sensor_group(agent, kind)}"


StreamClass = Literal["latest-wins", "must-deliver", "health"]
StreamKind = Literal["pubsub", "queryable", "liveliness"]
HeaderPlacement = Literal["body", "attachment"]


@dataclass(frozen=True)
class QosProfile:
    name: str
    priority: str  # zenoh.Priority member name, e.g. "DATA_HIGH"
    congestion_control: str  # zenoh.CongestionControl member name: "DROP" or "BLOCK"
    express: bool

    def publisher_kwargs(self) -> dict[str, Any]:
        return {
            "priority": getattr(zenoh.Priority, self.priority),
            "congestion_control": getattr(zenoh.CongestionControl, self.congestion_control),
            "express": self.express,
        }


@dataclass(frozen=True)
class Stream:
    """One row of the key-space table."""

    name: str
    key_template: str
    type_name: str | None
    stream_class: StreamClass
    qos: QosProfile
    kind: StreamKind = "pubsub"
    header: HeaderPlacement = "body"
    reply_type_name: str | None = None
    doc: str = ""
    #: verb (publish, subscribe, serve, query, token, watch) -> roles allowed (`role` or `role/kind`)
    access: dict[str, tuple[str, ...]] = dataclasses.field(default_factory=dict)
    history: bool = False  # must-deliver: a late joiner gets the publisher's cached samples at once

    @property
    def advanced(self) -> bool:
        """Carried by Zenoh's advanced publisher/subscriber (must-deliver pub/sub, `must_deliver:`)."""
        return self.stream_class == "must-deliver" and self.kind == "pubsub"

    @property
    def fields(self) -> tuple[str, ...]:
        return tuple(f for _, f, _, _ in string.Formatter().parse(self.key_template) if f)

    def key(self, **ids: str) -> str:
        """Concrete key with every placeholder filled by a validated id."""
        missing = set(self.fields) - ids.keys()
        extra = ids.keys() - set(self.fields)
        if missing or extra:
            raise ValueError(f"stream {self.name}: missing ids {sorted(missing)}, unexpected {sorted(extra)}")
        for field, value in ids.items():
            validate_id(value, field)
        return self.key_template.format(**ids)

    def pattern(self, **ids: str) -> str:
        """Key expression with unspecified placeholders as `*` (e.g. all cameras of one agent)."""
        for field, value in ids.items():
            if field not in self.fields:
                raise ValueError(f"stream {self.name} has no id {field!r}")
            validate_id(value, field)
        return self.key_template.format(**{f: ids.get(f, "*") for f in self.fields})

    def ids(self, key: str) -> dict[str, str] | None:
        """The ids of a concrete key of this stream (the inverse of `key`), None if it is not one."""
        template, chunks = self.key_template.split("/"), key.split("/")
        if len(template) != len(chunks):
            return None
        out: dict[str, str] = {}
        for pattern, chunk in zip(template, chunks, strict=True):
            if pattern.startswith("{") and pattern.endswith("}"):
                out[pattern[1:-1]] = chunk
            elif pattern != chunk:
                return None
        return out

    def id_of(self, key: str, field: str) -> str:
        """The id `field` of a concrete key of this stream, "" if `key` is not one."""
        return (self.ids(key) or {}).get(field, "")

    def matches(self, key: str) -> bool:
        return zenoh.KeyExpr(self.pattern()).intersects(zenoh.KeyExpr(key))

    @property
    def message_type(self) -> type[Message]:
        if self.type_name is None:
            raise ValueError(f"stream {self.name} carries no message")
        return message_type(self.type_name)

    @property
    def reply_type(self) -> type[Message]:
        if self.reply_type_name is None:
            raise ValueError(f"stream {self.name} has no reply type")
        return message_type(self.reply_type_name)


@dataclass(frozen=True)
class Limits:
    """The bus-wide input limits (`limits:` in proto/streams.yaml; units in the names)."""

    max_clock_skew_s: float
    order_reset_s: float
    max_objects_per_list: int
    min_tick_hz: float
    max_tick_hz: float
    max_plan_version: int
    max_claimed_plan_version: int
    max_grid_cells: int
    max_string_chars: int
    max_list_length: int

    def __post_init__(self) -> None:
        if min(self.max_clock_skew_s, self.order_reset_s, self.min_tick_hz) <= 0:
            raise ValueError("limits: times and rates must be > 0")
        if self.min_tick_hz > self.max_tick_hz:
            raise ValueError("limits: min_tick_hz > max_tick_hz")
        if self.max_objects_per_list < 1 or not 1 <= self.max_plan_version < 2**63:
            raise ValueError("limits: max_objects_per_list >= 1, max_plan_version in [1, 2^63)")
        if not 0 <= self.max_claimed_plan_version < self.max_plan_version:
            raise ValueError("limits: max_claimed_plan_version in [0, max_plan_version)")
        if min(self.max_grid_cells, self.max_string_chars, self.max_list_length) < 1:
            raise ValueError("limits: max_grid_cells, max_string_chars, max_list_length >= 1")


@functools.cache
def limits(path: Path = STREAMS_YAML) -> Limits:
    return Limits(**yaml.safe_load(path.read_text())["limits"])


@dataclass(frozen=True)
class MustDeliver:
    """Advanced publisher/subscriber settings of the must-deliver streams (streams.yaml `must_deliver`)."""

    cache_samples: int
    recovery_query_s: float

    def __post_init__(self) -> None:
        if self.cache_samples < 1 or self.recovery_query_s <= 0:
            raise ValueError("must_deliver: cache_samples must be >= 1 and recovery_query_s > 0")


@functools.cache
def must_deliver(path: Path = STREAMS_YAML) -> MustDeliver:
    return MustDeliver(**yaml.safe_load(path.read_text())["must_deliver"])


def validate_id(value: str, what: str = "id") -> str:
    if not isinstance(value, str) or not ID_PATTERN.match(value):
        raise ValueError(f"invalid {what} {value!r}: must match {ID_PATTERN.pattern}")
    return value


_RMMDET_MODULES = ("common", "geometry", "sensors", "perception", "traffic", "planning", "health", "sim")


@functools.cache
def message_type(full_name: str) -> type[Message]:
    """Generated class for a full protobuf name (`rmmdet.v1.X` or `foxglove.X`)."""
    package, _, name = full_name.rpartition(".")
    if package == "rmmdet.v1":
        for module in _RMMDET_MODULES:
            cls = getattr(importlib.import_module(f"rmmdet.v1.{module}_pb2"), name, None)
            if cls is not None:
                return cls
    elif package == "foxglove":
        try:
            foxglove_module = importlib.import_module(f"foxglove_schemas_protobuf.{name}_pb2")
        except ImportError:
            foxglove_module = None
        if foxglove_module is not None and hasattr(foxglove_module, name):
            return getattr(foxglove_module, name)
    raise KeyError(f"unknown message type {full_name!r}")


def all_rmmdet_message_types() -> list[type[Message]]:
    """Every message class of the rmmdet.v1 package (for round-trip tests and tools)."""
    out: list[type[Message]] = []
    for module_name in _RMMDET_MODULES:
        module = importlib.import_module(f"rmmdet.v1.{module_name}_pb2")
        for desc in module.DESCRIPTOR.message_types_by_name.values():
            out.append(getattr(module, desc.name))
    return out


def load_streams(path: Path = STREAMS_YAML) -> dict[str, Stream]:
    spec = yaml.safe_load(path.read_text())
    profiles = {
        name: QosProfile(name, p["priority"], p["congestion_control"], bool(p["express"]))
        for name, p in spec["qos_profiles"].items()
    }
    for profile in profiles.values():
        profile.publisher_kwargs()  # unknown enum names fail here, at load time
    streams: dict[str, Stream] = {}
    for name, s in spec["streams"].items():
        if s["class"] not in spec["classes"]:
            raise ValueError(f"stream {name}: unknown class {s['class']!r}")
        if not s["key"].startswith(spec["prefix"] + "/"):
            raise ValueError(f"stream {name}: key {s['key']!r} outside {spec['prefix']}")
        streams[name] = Stream(
            name=name,
            key_template=s["key"],
            type_name=s.get("type"),
            stream_class=s["class"],
            qos=profiles[s["qos"]],
            kind=s.get("kind", "pubsub"),
            header=s.get("header", "body"),
            reply_type_name=s.get("reply_type"),
            doc=s.get("doc", ""),
            access=_access(name, s.get("access", {}), spec.get("readers", []), s.get("kind", "pubsub")),
            history=bool(s.get("history", False)),
        )
        if streams[name].history and not streams[name].advanced:
            raise ValueError(f"stream {name}: history needs a must-deliver pub/sub stream")
    return streams


ACCESS_VERBS = {
    "pubsub": ("publish", "subscribe"),
    "queryable": ("serve", "query"),
    "liveliness": ("token", "watch"),
}


def _access(
    name: str, access: dict[str, list[str]], readers: list[str], kind: str
) -> dict[str, tuple[str, ...]]:
    """A stream's grants, checked: only its kind's verbs; the global readers subscribe to pub/sub."""
    verbs = ACCESS_VERBS[kind]
    unknown = access.keys() - set(verbs)
    if unknown:
        raise ValueError(f"stream {name}: access verbs {sorted(unknown)} not among {verbs}")
    out = {verb: tuple(access.get(verb, [])) for verb in verbs}
    if kind == "pubsub":
        out["subscribe"] = (*out["subscribe"], *(r for r in readers if r not in out["subscribe"]))
    return out


@functools.cache
def key_prefix(path: Path = STREAMS_YAML) -> str:
    """Every stream's key starts with it (streams.yaml `prefix`, e.g. `rmmdet/v1`)."""
    return str(yaml.safe_load(path.read_text())["prefix"])


def wide_key(stream: Stream) -> str:
    """The stream's whole key space: every placeholder `*`, trailing ones `**`
    (`rmmdet/v1/{scope}/@health/{service}/{instance}` -> `rmmdet/v1/*/@health/**`)."""
    chunks = stream.key_template.split("/")
    while chunks and chunks[-1].startswith("{"):
        chunks.pop()
    wide = "/".join("*" if c.startswith("{") else c for c in chunks)
    return wide + "/**" if len(chunks) < len(stream.key_template.split("/")) else wide


def data_keys() -> list[str]:
    """Every pub/sub stream's whole key space (`wide_key`), in streams.yaml order: what a reader (the
    recorder, `rmmdet record`) subscribes to, stream by stream (the access control grants readers no
    wider: shared/security/acl.py). Two of them intersect only in keys no stream has
    (`rmmdet/v1/*/capture_demand/**` and `rmmdet/v1/vehicles/*/plan_ack`)."""
    return [wide_key(s) for s in streams().values() if s.kind == "pubsub"]


@functools.cache
def readers(path: Path = STREAMS_YAML) -> tuple[str, ...]:
    """Roles that may subscribe to every pub/sub stream (streams.yaml `readers`)."""
    return tuple(yaml.safe_load(path.read_text()).get("readers", []))


@functools.cache
def streams() -> dict[str, Stream]:
    return load_streams()


def get_stream(name: str) -> Stream:
    try:
        return streams()[name]
    except KeyError:
        raise KeyError(f"unknown stream {name!r}; known: {sorted(streams())}") from None


def stream_for_key(key: str) -> Stream | None:
    """The stream whose key template matches a concrete key, if any."""
    for stream in streams().values():
        if stream.kind == "pubsub" and stream.matches(key):
            return stream
    return None


def producer_of(key: str) -> str:
    """The node (`scope/service/instance`, as in its presence token) that publishes `key`: a sensor
    group for sensor data, the agent's MEC for objects; the key itself for anything else."""
    for kind, stream in SENSOR_STREAM.items():
        ids = get_stream(stream).ids(key)
        if ids is not None:
            return sensor_group_source(ids["agent"], kind)
    ids = get_stream("objects").ids(key)
    if ids is not None:
        return f"{ids['agent']}/{names.MEC}/{ids['agent']}"
    return key


def markdown_table() -> str:
    """The key-space table embedded in docs/bus.md."""
    rows = [
        "| Key expression | Message | Stream class | QoS (priority, congestion, express) | Kind | Notes |",
        "|---|---|---|---|---|---|",
    ]
    for s in streams().values():
        msg = s.type_name or "—"
        if s.reply_type_name:
            msg += f" → {s.reply_type_name}"
        if s.header == "attachment":
            msg += " (header in attachment)"
        qos = f"{s.qos.name}: {s.qos.priority}, {s.qos.congestion_control}, express={s.qos.express}"
        rows.append(f"| `{s.key_template}` | `{msg}` | {s.stream_class} | {qos} | {s.kind} | {s.doc} |")
    return "\n".join(rows) + "\n"


#: How the diagram names each role of `access` (a sensor kind is drawn with its group).
ROLE_LABELS = {
    "sensors": "sensor groups",
    "mec": "MEC (one per agent)",
    "coordinator": "coordinator (or its region shards)",
    "sim": "sim",
    "vehicles": "vehicles",
    "readers": "viewer, recorder, operators",
}


def diagram() -> str:
    """The processes and the data between them as a Mermaid flowchart, from `access` in streams.yaml:
    an arrow from the role that publishes a stream to each role that subscribes to it (streams no role
    subscribes to go to the readers: viewer, recorder, operators), a dotted one from the role that
    queries an RPC to the one that serves it. Presence and health, which every service has, are left
    out."""
    edges: dict[tuple[str, str, bool], list[str]] = {}
    wide = set(readers())  # roles that read everything: drawn once, as the readers
    for s in streams().values():
        if s.kind == "pubsub":
            sources, rpc = s.access.get("publish", ()), False
            targets = tuple(r for r in s.access.get("subscribe", ()) if r not in wide) or ("readers",)
        elif s.kind == "queryable" and s.name != "health":
            sources, targets, rpc = s.access.get("query", ()), s.access.get("serve", ()), True
        else:
            continue
        for a in sorted({r.split("/")[0] for r in sources}):
            for b in sorted({r.split("/")[0] for r in targets}):
                edges.setdefault((a, b, rpc), []).append(s.name)
    lines = ["```mermaid", "flowchart LR"]
    lines += [f'  {role}["{label}"]' for role, label in ROLE_LABELS.items()]
    for (a, b, rpc), stream_names in sorted(edges.items()):
        arrow = "-.->" if rpc else "-->"
        lines.append(f"  {a} {arrow}|{', '.join(stream_names)}| {b}")
    return "\n".join([*lines, "```"]) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--markdown", action="store_true", help="print the key-space table")
    parser.add_argument("--diagram", action="store_true", help="print the processes-and-streams diagram")
    args = parser.parse_args()
    if args.markdown:
        print(markdown_table(), end="")
    elif args.diagram:
        print(diagram(), end="")
    else:
        for s in streams().values():
            print(f"{s.name:16s} {s.key_template}")


if __name__ == "__main__":
    main()
