"""A URDF's XML: parsed for editing and written back with the user's namespace prefixes.

ElementTree renames every namespace prefix it writes (``xmlns:sensor`` becomes ``xmlns:ns0``, and
``<sensor:camera>`` ``<ns0:camera>``), which breaks readers that match tag names literally (urdfdom's
TinyXML, Gazebo copying ``<gazebo>`` blocks). :func:`urdf_to_text` writes them back as the source
declared them.
"""

from __future__ import annotations

import io
import re
import xml.etree.ElementTree as ET

from graphcal.errors import ModelError

__all__ = ["parse_urdf", "urdf_to_text"]


def parse_urdf(urdf_xml: str, *, comments: bool = False) -> ET.Element:
    """The ``<robot>`` element of a URDF string (``comments``: keep ``<!-- -->`` as elements).

    Raises:
        ModelError: not valid XML, or the root element is not ``<robot>``.
    """
    parser = ET.XMLParser(target=ET.TreeBuilder(insert_comments=True)) if comments else None
    try:
        root = ET.fromstring(urdf_xml, parser=parser)
    except ET.ParseError as exc:
        raise ModelError(f"URDF is not valid XML: {exc}") from None
    if root.tag != "robot":
        raise ModelError(f"not a URDF: root element is <{root.tag}>, expected <robot>")
    return root


def _declared_prefixes(urdf_xml: str) -> list[tuple[str, str]]:
    """(prefix, uri) of every ``xmlns:prefix`` declared in the source, document order."""
    out = []
    for _, (prefix, uri) in ET.iterparse(io.StringIO(urdf_xml), events=("start-ns",)):
        if prefix and (prefix, uri) not in out:
            out.append((prefix, uri))
    return out


def urdf_to_text(root: ET.Element, source_xml: str) -> str:
    """``root`` as XML text, namespace prefixes spelled as ``source_xml`` declared them.

    ElementTree's prefix table is global: the source's prefixes are registered in it (a prefix
    ElementTree reserves, ``ns<digits>`` or ``xml``, is left to ElementTree's own naming)."""
    for prefix, uri in _declared_prefixes(source_xml):
        if re.fullmatch(r"ns\d+", prefix) or prefix.lower().startswith("xml"):
            continue
        ET.register_namespace(prefix, uri)
    return ET.tostring(root, encoding="unicode")
