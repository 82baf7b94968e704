"""The exported NodeSet2 imports into strict tools (issue 43, "A NodeSet2 that imports"): 0 errors against
the OPC Foundation's UANodeSet.xsd and Opc.Ua.Types.xsd (lxml), open62541's nodeset compiler (``o6-ncc``)
exits 0, a ``<Models>`` element names the model, and the methods are in the file when they are served,
with string NodeIds for their arguments. The file before this change had 292 schema errors (``nan``,
``1601-01-01 00:00:00+00:00``) and properties in namespace 0 (``i=20001``) that the compiler refused."""

from __future__ import annotations

import asyncio
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from asyncua import Server, ua

from service.cli import main as chtc
from service.serve.opcua.nodes import MODEL_VERSION
from service.serve.opcua.nodeset import xs_datetime, xs_double
from tests.opcua.nodeset_check import compile_nodeset, xsd_errors

NS = "http://opcfoundation.org/UA/2011/03/UANodeSet.xsd"
URI = "urn:spindle-chtc:opcua"


def _export(tmp_path: Path, toml: str) -> Path:
    config = tmp_path / "chtc.toml"
    config.write_text(toml, encoding="utf-8")
    out = tmp_path / "chtc.NodeSet2.xml"
    assert chtc(["opcua", "nodeset", "--out", str(out), "--config", str(config)]) == 0
    return out


def _cell_toml(n: int) -> str:
    """A cell of ``n`` spindles as ``chtc bench fleet`` names them (one DAQ port and CAN channel each)."""
    entries = "".join(
        f'[[spindles]]\nid = "sp{i:02d}"\nmodbus = {{port = {5100 + i}}}\ncan = {{channel = "vcan{i}"}}\n'
        for i in range(1, n + 1)
    )
    return "[opcua]\nmethods = true\n" + entries


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _export(tmp_path_factory.mktemp("cell"), _cell_toml(10))


@pytest.fixture(scope="module")
def with_methods(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _export(tmp_path_factory.mktemp("ns"), '[spindle]\nid = "Spindle1"\n[opcua]\nmethods = true\n')


def test_the_schema_spellings() -> None:
    assert [xs_double(x) for x in ("nan", "inf", "-inf", "1.5", "-2000.0")] == [
        "NaN",
        "INF",
        "-INF",
        "1.5",
        "-2000.0",
    ]
    assert xs_datetime("1601-01-01 00:00:00+00:00") == "1601-01-01T00:00:00Z"
    assert xs_datetime("2026-11-29 10:00:00.250000+01:00") == "2026-11-29T09:00:00.250000Z"


@pytest.mark.parametrize("methods", [False, True])
def test_the_nodeset_is_valid_against_both_opc_foundation_schemas(tmp_path: Path, methods: bool) -> None:
    out = _export(tmp_path, f"[opcua]\nmethods = {str(methods).lower()}\n")
    assert xsd_errors(out) == []
    text = out.read_text(encoding="utf-8")
    assert ">nan<" not in text and "Historizing" not in text  # no history is served
    assert ("StartIdentification" in text) is methods


def test_the_models_element_names_the_model(with_methods: Path) -> None:
    root = ET.parse(with_methods).getroot()
    children = [c.tag.split("}")[1] for c in root][:3]
    assert children == ["NamespaceUris", "Models", "Aliases"]  # the schema's order
    model = root.find(f"{{{NS}}}Models/{{{NS}}}Model")
    assert model is not None
    assert model.get("ModelUri") == URI and model.get("Version") == MODEL_VERSION
    assert model.get("PublicationDate", "").endswith("T00:00:00Z")
    required = model.find(f"{{{NS}}}RequiredModel")
    assert required is not None and required.get("ModelUri") == "http://opcfoundation.org/UA/"


def test_the_methods_and_their_arguments_have_stable_string_node_ids(with_methods: Path) -> None:
    root = ET.parse(with_methods).getroot()
    methods = {m.get("NodeId") for m in root.iter(f"{{{NS}}}UAMethod")}
    assert methods == {"ns=1;s=Spindle1.StartIdentification", "ns=1;s=Spindle1.TakeSensorBaseline"}
    ids = [v.get("NodeId", "") for v in root.iter(f"{{{NS}}}UAVariable")]
    assert "ns=1;s=Spindle1.StartIdentification.InputArguments" in ids
    assert "ns=1;s=Spindle1.TakeSensorBaseline.OutputArguments" in ids
    assert all(";s=" in i for i in ids), [i for i in ids if ";s=" not in i]  # no numeric NodeIds
    assert not [i for i in ids if i.startswith("i=") or ";i=" in i]

    async def load() -> list[ua.Argument]:
        server = Server()
        await server.init()
        await server.import_xml(str(with_methods))
        idx = await server.get_namespace_index(URI)
        node = server.get_node(f"ns={idx};s=Spindle1.StartIdentification.InputArguments")
        return list(await node.read_value())

    (reason,) = asyncio.run(load())
    assert reason.Name == "Reason" and reason.DataType == ua.NodeId(ua.ObjectIds.String)


@pytest.mark.slow
def test_open62541s_nodeset_compiler_compiles_it(with_methods: Path, tmp_path: Path) -> None:
    done = compile_nodeset(with_methods, tmp_path / "ncc")
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    assert list((tmp_path / "ncc" / "c").glob("*.c"))


def test_a_cell_has_one_object_per_spindle_of_one_type_and_is_valid(cell: Path) -> None:
    assert xsd_errors(cell) == []
    root = ET.parse(cell).getroot()
    objects = [o for o in root.iter(f"{{{NS}}}UAObject") if o.get("ParentNodeId") == "i=85"]
    assert [o.get("NodeId") for o in objects] == [f"ns=1;s=sp{i:02d}" for i in range(1, 11)]
    for o in objects:
        refs = o.find(f"{{{NS}}}References")
        assert refs is not None
        typedefs = [r.text for r in refs if r.get("ReferenceType") == "HasTypeDefinition"]
        assert typedefs == ["ns=1;s=SpindleThermalModelType"]
    ids = {v.get("NodeId") for v in root.iter(f"{{{NS}}}UAVariable")}
    assert (
        "ns=1;s=sp02.Controller.SD43900Mm" in ids and "ns=1;s=sp10.StartIdentification.InputArguments" in ids
    )
    assert len(list(root.iter(f"{{{NS}}}UAMethod"))) == 20


def test_a_cell_refuses_one_object_name_for_every_spindle(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "chtc.toml"
    config.write_text(_cell_toml(2).replace("methods = true", 'spindle = "Spindle1"'), encoding="utf-8")
    assert chtc(["opcua", "nodeset", "--out", str(tmp_path / "x.xml"), "--config", str(config)]) == 2
    assert "opcua.spindle" in capsys.readouterr().err


@pytest.mark.slow
def test_open62541s_nodeset_compiler_compiles_a_cell(cell: Path, tmp_path: Path) -> None:
    done = compile_nodeset(cell, tmp_path / "ncc")
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
