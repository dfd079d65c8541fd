"""The sim's fleet of connected vehicles (services/sim): what it needs to start."""

from __future__ import annotations


def test_the_sim_refuses_to_start_without_an_identity_for_each_vehicle(tmp_path, capfd) -> None:
    """`--vehicle-configs`: every vehicle drives under its own identity; one missing is a clear exit 2
    (it could not ask for plans: the sim's identity holds no vehicle's rights), before any session."""
    from services.sim.main import cli

    (tmp_path / "vehicle-v00.json").write_text("{}")
    rc = cli(["--vehicles", "2", "--vehicle-configs", str(tmp_path)])
    assert rc == 2
    assert "no identity config for vehicles ['v01']" in capfd.readouterr().err
