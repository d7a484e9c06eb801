"""The imitation diagram's picture in README: drawn from the diagram, and
current."""

from pathlib import Path

import pytest
from fabric_imitation.tools.picture import DiagramDot, ImitationDiagramDot, RenderSvg
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import Adder, ConstantVectorSource

PICTURE = Path(__file__).resolve().parent.parent / "docs" / "imitation_diagram.svg"


def _small_diagram():
    builder = DiagramBuilder()
    source = builder.AddNamedSystem("source", ConstantVectorSource([1.0]))
    adder = builder.AddNamedSystem("a|b", Adder(2, 1))
    builder.Connect(source.get_output_port(), adder.get_input_port(1))
    builder.ExportInput(adder.get_input_port(0), "u")
    diagram = builder.Build()
    diagram.set_name("small")
    return diagram


def test_the_picture_shows_each_system_its_ports_and_connections():
    dot = DiagramDot(_small_diagram())
    assert dot == DiagramDot(_small_diagram())  # no ids that change
    assert 'n0 [label="{{}|source\\n(ConstantVectorSource)|{<y0> y0}}"];' in dot
    assert 'n1 [label="{{<u0> u0|<u1> u1}|a\\|b\\n(Adder)|{<y0> sum}}"];' in dot
    assert "n0:y0 -> n1:u1;" in dot
    svg = RenderSvg(dot).decode()
    assert "<svg" in svg and "ConstantVectorSource" in svg


@pytest.mark.slow
def test_readme_picture_is_the_current_imitation_diagram():
    committed = PICTURE.with_suffix(".dot").read_text()
    assert ImitationDiagramDot("box") == committed, (
        "the imitation diagram changed: run `fabric-imitate diagram "
        "--out docs/imitation_diagram.svg`"
    )
