"""The key space: builders, validation, message types, and docs/bus.md kept in sync."""

from __future__ import annotations

import pytest
import zenoh

from shared.bus.liveliness import agent_of_mec_token
from shared.bus.streams import (
    diagram,
    get_stream,
    markdown_table,
    message_type,
    producer_of,
    stream_for_key,
    streams,
)
from tests.helpers import REPO_ROOT


def test_keys_are_built_and_validated() -> None:
    assert get_stream("objects").key(agent="agent1") == "rmmdet/v1/agent1/objects"
    assert (
        get_stream("camera_image").key(agent="agent1", sensor="cam_11")
        == "rmmdet/v1/agent1/sensor/camera/cam_11"
    )
    assert get_stream("camera_image").pattern(agent="agent2") == "rmmdet/v1/agent2/sensor/camera/*"
    for bad in ("Agent1", "a/b", "a*", "", "@x", "a b", "a$"):
        with pytest.raises(ValueError, match="invalid"):
            get_stream("objects").key(agent=bad)
    with pytest.raises(ValueError, match="missing ids"):
        get_stream("camera_image").key(agent="agent1")
    with pytest.raises(ValueError, match="unexpected"):
        get_stream("objects").key(agent="agent1", sensor="x")


def test_every_key_is_a_valid_canonical_key_expression() -> None:
    for stream in streams().values():
        ids = {f: "x1" for f in stream.fields}
        key = stream.key(**ids)
        assert str(zenoh.KeyExpr(key)) == key
        assert key.startswith("rmmdet/v1/")


def test_data_wildcard_excludes_control_keys() -> None:
    """`rmmdet/v1/**` must not reach @health/@alive/@rpc: verbatim chunks stop wildcards."""
    data = zenoh.KeyExpr("rmmdet/v1/**")
    for name in ("health", "alive", "route_rpc"):
        s = get_stream(name)
        assert not data.intersects(zenoh.KeyExpr(s.key(**{f: "x1" for f in s.fields})))
    assert data.intersects(zenoh.KeyExpr(get_stream("objects").key(agent="agent1")))


def test_every_stream_type_resolves() -> None:
    for stream in streams().values():
        if stream.type_name:
            assert stream.message_type.DESCRIPTOR.full_name == stream.type_name
        if stream.reply_type_name:
            assert stream.reply_type.DESCRIPTOR.full_name == stream.reply_type_name
    with pytest.raises(KeyError):
        message_type("rmmdet.v1.Nope")


def test_stream_for_key() -> None:
    assert stream_for_key("rmmdet/v1/agent3/sensor/lidar/lidar_41").name == "point_cloud"
    assert stream_for_key("rmmdet/v1/cloud/plans/veh_01").name == "route_plan"
    assert stream_for_key("rmmdet/v1/unknown/thing") is None


def test_proto_readme_table_is_current() -> None:
    readme = (REPO_ROOT / "docs" / "bus.md").read_text()
    assert markdown_table() in readme, "regenerate: python -m shared.bus.streams --markdown"


def test_architecture_diagram_is_current() -> None:
    page = (REPO_ROOT / "docs" / "architecture.md").read_text()
    assert diagram() in page, "regenerate: python -m shared.bus.streams --diagram"


def test_the_diagram_draws_each_data_stream_from_its_publishers() -> None:
    text = diagram()
    assert "  mec -->|objects| coordinator" in text
    assert "  vehicles -.->|route_rpc| coordinator" in text  # a query, dotted, toward who serves it
    assert "health" not in text and "alive" not in text  # every service has them: not drawn


def test_ids_inverts_key() -> None:
    alive = get_stream("alive")
    ids = {"scope": "agent2", "service": "mec", "instance": "agent2"}
    assert alive.ids(alive.key(**ids)) == ids
    assert get_stream("objects").ids("rmmdet/v1/agent1/objects") == {"agent": "agent1"}
    assert get_stream("objects").ids("rmmdet/v1/agent1/objects/extra") is None  # other length
    assert get_stream("objects").ids("rmmdet/@v2/agent1/objects") is None  # other literal chunk
    assert get_stream("route_ack").ids("rmmdet/v1/agent1/objects") is None


def test_id_of_and_mec_tokens() -> None:
    assert get_stream("objects").id_of("rmmdet/v1/agent2/objects", "agent") == "agent2"
    assert get_stream("route_ack").id_of("rmmdet/v1/vehicles/v07/plan_ack", "vehicle") == "v07"
    assert get_stream("objects").id_of("rmmdet/v1/vehicles/v07/plan_ack", "agent") == ""
    assert agent_of_mec_token("rmmdet/v1/agent3/@alive/mec/agent3") == "agent3"
    assert agent_of_mec_token("rmmdet/v1/agent3/@alive/mec/agent1") is None
    assert agent_of_mec_token("rmmdet/v1/site/@alive/router/main") is None


def test_producer_of_names_the_publishing_node() -> None:
    camera_key = get_stream("camera_image").key(agent="agent2", sensor="cam_21")
    assert producer_of(camera_key) == "agent2/sensor/agent2-cameras"
    assert producer_of("rmmdet/v1/agent3/objects") == "agent3/mec/agent3"
    assert producer_of("rmmdet/v1/cloud/maps/traffic") == "rmmdet/v1/cloud/maps/traffic"
