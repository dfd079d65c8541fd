"""Session configs from the standard Zenoh flags: enforced settings win, and key or certificate files
that cannot be read are named before any connection is tried."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from shared.bus.zenoh_config import missing_files, zenoh_config


def test_enforced_settings_win_over_the_flags() -> None:
    conf = zenoh_config(None, cfg=["scouting/multicast/enabled:true", "transport/shared_memory/enabled:true"])
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("transport/shared_memory/enabled")) is False


def test_a_malformed_override_is_refused() -> None:
    with pytest.raises(ValueError, match="KEY:VALUE"):
        zenoh_config(None, cfg=["mode"])


def test_unreadable_key_and_certificate_files_are_named(tmp_path: Path) -> None:
    present = tmp_path / "ca.pem"
    present.write_text("-----BEGIN CERTIFICATE-----\n")
    gone = tmp_path / "key.pem"
    conf = zenoh_config(
        None,
        cfg=[
            f'transport/link/tls/root_ca_certificate:"{present}"',
            f'transport/link/tls/connect_private_key:"{gone}"',
        ],
    )
    assert missing_files(conf) == [f"transport/link/tls/connect_private_key: no readable file {gone}"]
    assert missing_files(zenoh_config(None)) == []  # plain TCP names no files
