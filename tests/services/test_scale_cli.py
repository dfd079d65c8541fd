"""`rmmdet scale`: a scene's factors and its scaled settings; the docs' table is the code's."""

from __future__ import annotations

from typer.testing import CliRunner

from services.cli.main import app
from services.cli.scale import README_SCENE, SECTION, markdown
from shared.paths import DEFAULT_SCENE
from shared.readme import markers, section_file
from shared.scene.scene import Scene


def test_the_docs_table_is_what_the_code_derives() -> None:
    begin, end = markers(SECTION)
    text = section_file(SECTION).read_text()
    body = text.split(begin, 1)[1].split(end, 1)[0].strip().rsplit("\n\n", 1)[0]  # less the provenance line
    site = Scene.load(README_SCENE)
    expected = markdown(site, next(iter(site.agents)), Scene.load(DEFAULT_SCENE))
    assert body == expected, "regenerate: .venv/bin/rmmdet scale --readme"


def test_the_command_shows_the_factors_and_the_settings() -> None:
    result = CliRunner().invoke(app, ["scale", "--scene", str(README_SCENE)])
    assert result.exit_code == 0, result.output
    assert "length x13.64, speed x27.8, acceleration x4.167" in result.output
    assert "tracker.gate_m" in result.output and "6.818" in result.output  # 0.5 m x 13.64
    assert "vehicles: car (reference) 4.5 x 1.8 x 1.5 m 70%, van" in result.output
    assert "truck 8.5 x 2.5 x 3.2 m 10%" in result.output
    table = CliRunner().invoke(app, ["scale"])
    assert table.exit_code == 0 and "length x1, speed x1, acceleration x1" in table.output


def test_an_unknown_agent_is_refused() -> None:
    result = CliRunner().invoke(app, ["scale", "--agent", "agent9"])
    assert result.exit_code == 2 and "agent9 is not an agent" in result.output
