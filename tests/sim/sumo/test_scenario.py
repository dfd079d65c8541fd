"""A SUMO scenario read as SUMO reads it (`.sumocfg`: net, route files, additional files, times), and
every way it can be wrong a one-line error naming the file and element (issue 53 items 1 and 6)."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import libsumo
import pytest

from sim.sumo import demand, network
from sim.sumo.scenario import ScenarioError, load_scenario
from sim.sumo.world import SumoWorld

VTYPES = '<additional><vType id="Bologna_car" length="4.2" maxSpeed="13.9" accel="2.0"/></additional>\n'


def config(folder: Path, net: str, routes: str, additional: str = "", end: str = "600") -> Path:
    path = folder / "run.sumocfg"
    extra = f'<additional-files value="{additional}"/>' if additional else ""
    path.write_text(
        f'<configuration><input><net-file value="{net}"/><route-files value="{routes}"/>{extra}</input>'
        f'<time><begin value="0"/><end value="{end}"/></time></configuration>\n'
    )
    return path


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("scenario")
    net = network.grid_network(network.GridSpec(junctions_per_side=3), folder / "grid.net.xml")
    spec = demand.DemandSpec(vehicles=10, end_s=20.0, min_distance_m=100.0)
    routes = demand.routed_demand(net, spec, 1, folder / "plain.rou.xml")
    tree = ET.parse(routes)
    for vehicle in tree.getroot().iter("vehicle"):
        vehicle.set("type", "Bologna_car")
    tree.write(folder / "typed.rou.xml")
    (folder / "vtypes.add.xml").write_text(VTYPES)
    return folder


def test_a_configuration_runs_with_its_additional_files(folder: Path) -> None:
    scenario = load_scenario(config(folder, "grid.net.xml", "typed.rou.xml", "vtypes.add.xml", "0:10:00"))
    assert scenario.net == (folder / "grid.net.xml").resolve() and scenario.end_s == 600.0
    assert [p.name for p in scenario.additional] == ["vtypes.add.xml"]
    with SumoWorld(scenario.net, scenario.routes, seed=1, additional=scenario.additional) as world:
        while world.running() == 0 and world.time_s < 60:
            world.step()
        assert {libsumo.vehicle.getTypeID(v) for v in world.vehicles().ids} == {"Bologna_car"}


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (None, "no such scenario configuration"),
        ("<configuration><input>", "not a SUMO configuration"),
        ("<routes/>", "expected one of"),
        ("<configuration><input/></configuration>", "exactly one net"),
        (
            '<configuration><input><net-file value="grid.net.xml"/><route-files value="gone.rou.xml"/>'
            "</input></configuration>",
            "<route-files> names 'gone.rou.xml'",
        ),
        (
            '<configuration><input><net-file value="grid.net.xml"/></input><time><end value="soon"/></time>'
            "</configuration>",
            "<end value='soon'> is not a time",
        ),
    ],
)
def test_a_bad_configuration_is_one_line_naming_file_and_element(
    folder: Path, tmp_path: Path, text: str | None, message: str
) -> None:
    path = tmp_path / "bad.sumocfg"
    if text is not None:
        path.write_text(text.replace("grid.net.xml", str(folder / "grid.net.xml")))
    with pytest.raises(ScenarioError, match=message.replace("(", r"\(")) as err:
        load_scenario(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_what_sumo_refuses_is_an_error_with_its_own_words(folder: Path, tmp_path: Path) -> None:
    """A net SUMO cannot read (SUMO itself crashes on this one: in libsumo it took the test process
    down), and a route whose vType no file defines: SUMO's message or how it died, no hang."""
    garbage = tmp_path / "garbage.net.xml"
    garbage.write_text("<net><edge id='e' from='nowhere'/></net>\n")
    for net, routes in (
        (garbage, folder / "plain.rou.xml"),
        (folder / "grid.net.xml", folder / "typed.rou.xml"),
    ):
        with pytest.raises(ScenarioError, match=r"SUMO (refused|crashed)") as err:
            SumoWorld(net, routes, seed=1)
        assert str(net) in str(err.value)
    with SumoWorld(folder / "grid.net.xml", folder / "plain.rou.xml", seed=1) as world:  # usable after
        world.step()


def test_an_unknown_vtype_is_named_in_sumos_words(folder: Path) -> None:
    with pytest.raises(ScenarioError, match=r"vehicle type 'Bologna_car' .* is not known"):
        SumoWorld(folder / "grid.net.xml", folder / "typed.rou.xml", seed=1)


def test_a_route_that_does_not_connect_is_named_in_sumos_words(folder: Path, tmp_path: Path) -> None:
    """Two edges of the grid that do not meet as one vehicle's route: SUMO's words name both edges."""
    import sumolib

    net = sumolib.net.readNet(str(folder / "grid.net.xml"))
    first = next(e for e in net.getEdges() if e.getFunction() != "internal")
    apart = next(
        e
        for e in net.getEdges()
        if e.getFunction() != "internal"
        and e.getFromNode() not in (first.getToNode(), first.getFromNode())
        and e not in first.getOutgoing()
    )
    routes = tmp_path / "broken.rou.xml"
    routes.write_text(
        f'<routes><vehicle id="Audinot_1" depart="0"><route edges="{first.getID()} {apart.getID()}"/>'
        "</vehicle></routes>\n"
    )
    with pytest.raises(ScenarioError, match="SUMO refused them") as err:
        SumoWorld(folder / "grid.net.xml", routes, seed=1)
    message = str(err.value)
    assert str(routes) in message and first.getID() in message and apart.getID() in message, message
