"""Independent checks of a NodeSet2 file, as a strict engineering tool would make them.

- :func:`xsd_errors`: lxml with the OPC Foundation's ``UANodeSet.xsd`` and ``Opc.Ua.Types.xsd``
  (``tests/opcua/schemas``). The NodeSet schema leaves ``<Value>`` lax; a wrapper schema that imports both
  makes lxml validate every value's elements (``uax:Double``, ``uax:DateTime``, ``uax:EUInformation``, ...)
  against the types schema too.
- :func:`compile_nodeset`: open62541's nodeset compiler (``ncc c`` from the ``o6-ncc`` package) with the
  base namespace it bundles (``ns0``) as the existing nodes; it must exit 0.
"""

from __future__ import annotations

import gzip
import shutil
import subprocess
import sys
from importlib.resources import files
from pathlib import Path

from lxml import etree

SCHEMAS = Path(__file__).parent / "schemas"
_WRAPPER = f"""<xs:schema xmlns:xs="http://www.w3.org/2001/XMLSchema">
  <xs:import namespace="http://opcfoundation.org/UA/2011/03/UANodeSet.xsd"
             schemaLocation="{(SCHEMAS / "UANodeSet.xsd").as_uri()}"/>
  <xs:import namespace="http://opcfoundation.org/UA/2008/02/Types.xsd"
             schemaLocation="{(SCHEMAS / "Opc.Ua.Types.xsd").as_uri()}"/>
</xs:schema>"""


def xsd_errors(path: Path) -> list[str]:
    """Every schema error of the NodeSet2 file ``path`` (``line: message``); empty: valid."""
    schema = etree.XMLSchema(etree.fromstring(_WRAPPER.encode()))
    doc = etree.parse(str(path))
    schema.validate(doc)
    return [f"{e.line}: {e.message}" for e in schema.error_log]


def _ncc() -> str:
    exe = shutil.which("ncc") or str(Path(sys.executable).with_name("ncc"))
    if not Path(exe).exists():
        raise FileNotFoundError("ncc (pip install o6-ncc, the test extra)")
    return exe


def compile_nodeset(path: Path, out: Path) -> subprocess.CompletedProcess[str]:
    """``ncc c -e <ns0> -o out path``: open62541's nodeset compiler to C."""
    out.mkdir(parents=True, exist_ok=True)
    ns0 = out / "ns0.xml"
    ns0.write_bytes(gzip.decompress(files("o6_nodeset_compiler").joinpath("bundle/ns0.xml.gz").read_bytes()))
    return subprocess.run(
        [_ncc(), "c", "-e", str(ns0), "-o", str(out / "c"), str(path)],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
