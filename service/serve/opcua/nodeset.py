"""The NodeSet2 XML a strict tool imports (pure: text in, text out; stdlib ElementTree).

asyncua's exporter writes what the OPC Foundation's schemas refuse (``Opc.Ua.Types.xsd``): ``nan`` for a
Double (the schema's xs:double spells it ``NaN``, ``INF``, ``-INF``) and ``1601-01-01 00:00:00+00:00`` for
a DateTime (xs:dateTime needs the ``T``), and no ``<Models>`` element (``UANodeSet.xsd``), which TIA
Portal, SiOME and UaModeler read to know which model and version they import. :func:`conform` mends the
text asyncua wrote:

- the placeholder values of the data variables (NaN, the 1601 epoch, empty strings: the server's "waiting
  for initial data") are dropped: a value there means nothing, and a NodeSet's ``<Value>`` is optional.
  Properties (``HasTypeDefinition`` PropertyType: EngineeringUnits, EURange, Input/OutputArguments) keep
  theirs;
- any Double/Float and DateTime still written is spelled as the schema spells it;
- a ``<Models>`` element names the model (URI, version, publication date) and the OPC UA base model it
  requires.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from datetime import UTC, datetime

__all__ = ["BASE_MODEL_URI", "BASE_MODEL_VERSION", "Model", "conform"]

NS = "http://opcfoundation.org/UA/2011/03/UANodeSet.xsd"
TYPES = "http://opcfoundation.org/UA/2008/02/Types.xsd"
BASE_MODEL_URI = "http://opcfoundation.org/UA/"
# AnalogUnitRangeType (i=17570) is in the base model from 1.04 on (published 2017-11-22)
BASE_MODEL_VERSION = "1.04"
BASE_MODEL_PUBLISHED = "2017-11-22T00:00:00Z"
PROPERTY_TYPE = "i=68"
_PREFIXES = {
    "": NS,
    "uax": TYPES,
    "xsi": "http://www.w3.org/2001/XMLSchema-instance",
    "xsd": "http://www.w3.org/2001/XMLSchema",
}


@dataclass(frozen=True)
class Model:
    """The ``<Model>`` of our namespace: its URI, version and publication date (UTC)."""

    uri: str
    version: str
    published: datetime


def _q(tag: str, ns: str = NS) -> str:
    return f"{{{ns}}}{tag}"


def xs_double(text: str) -> str:
    """``text`` (a Python float's ``str``) as xs:double spells it: ``NaN``, ``INF``, ``-INF``, else as is."""
    x = float(text)
    if math.isnan(x):
        return "NaN"
    if math.isinf(x):
        return "INF" if x > 0 else "-INF"
    return text


def xs_datetime(text: str) -> str:
    """``text`` (``str(datetime)`` or ISO 8601) as xs:dateTime in UTC: ``1601-01-01T00:00:00Z``."""
    t = datetime.fromisoformat(text.strip())
    t = t.replace(tzinfo=UTC) if t.tzinfo is None else t.astimezone(UTC)
    return t.isoformat(timespec="microseconds" if t.microsecond else "seconds").replace("+00:00", "Z")


def _is_property(var: ET.Element) -> bool:
    refs = var.find(_q("References"))
    return refs is not None and any(
        r.get("ReferenceType") == "HasTypeDefinition" and (r.text or "").strip() == PROPERTY_TYPE
        for r in refs.iter(_q("Reference"))
    )


def conform(xml: str, model: Model) -> str:
    """The NodeSet2 ``xml`` (asyncua's export) mended as the module docstring says."""
    for prefix, uri in _PREFIXES.items():
        ET.register_namespace(prefix, uri)
    root = ET.fromstring(xml)
    for var in root.iter(_q("UAVariable")):
        value = var.find(_q("Value"))
        if value is not None and not _is_property(var):
            var.remove(value)
    for tag in ("Double", "Float"):
        for el in root.iter(_q(tag, TYPES)):
            el.text = xs_double(el.text or "nan")
    for el in root.iter(_q("DateTime", TYPES)):
        el.text = xs_datetime(el.text or "1601-01-01T00:00:00+00:00")
    _set_models(root, model)
    ET.indent(root, space="  ")
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def _set_models(root: ET.Element, model: Model) -> None:
    old = root.find(_q("Models"))
    if old is not None:
        root.remove(old)
    models = ET.Element(_q("Models"))
    entry = ET.SubElement(
        models,
        _q("Model"),
        {
            "ModelUri": model.uri,
            "Version": model.version,
            "PublicationDate": xs_datetime(model.published.isoformat()),
        },
    )
    ET.SubElement(
        entry,
        _q("RequiredModel"),
        {"ModelUri": BASE_MODEL_URI, "Version": BASE_MODEL_VERSION, "PublicationDate": BASE_MODEL_PUBLISHED},
    )
    # UANodeSet.xsd's order: NamespaceUris, ServerUris, Models, Aliases, ...
    at = 0
    for i, child in enumerate(list(root)):
        if child.tag in (_q("NamespaceUris"), _q("ServerUris")):
            at = i + 1
    root.insert(at, models)
