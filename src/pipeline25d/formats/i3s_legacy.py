"""I3S 1.6 node index documents, read as :mod:`.i3s` reads 1.7 node pages.

A layer without ``nodePages`` (I3S 1.6 and older; ArcGIS Pro wrote them until 2019, and a 1.7
package keeps them beside its pages) has one ``nodes/<id>/3dNodeIndexDocument.json`` per node: its
bounding sphere ``mbs`` (lon, lat or x, y, z, radius: positions are offsets from its centre),
``lodSelection`` (``maxScreenThreshold``: a diameter in pixels, or its ``SQ`` area), ``children``
(ids and hrefs), ``geometryData`` and ``textureData`` hrefs. The geometry buffer's layout is the
store's ``defaultGeometrySchema``; its ``region`` attribute is present only where the node's
material says ``vertexRegions``, so it is taken where the buffer's length holds it, as clients do.
Each document becomes the node dict :func:`pipeline25d.formats.i3s.drawn_nodes` walks.
"""

from __future__ import annotations

import posixpath

from pipeline25d.core.errors import InputFileError
from pipeline25d.formats.slpk import Package

#: 1.6 attribute names -> the geometry buffer keys of 1.7
_KEYS = {"region": "uvRegion", "id": "featureId"}


class NodeDocuments:
    """The layer's nodes by id (``root`` first), each document read when first needed."""

    root = "root"

    def __init__(self, package: Package, store: dict):
        self.package = package
        root = store.get("rootNode") if isinstance(store.get("rootNode"), str) else "./nodes/root"
        self.root = _folder(posixpath.normpath(root.lstrip("./") or "nodes/root"))

    def __getitem__(self, node_id: str) -> dict:
        try:
            return self._node(node_id)
        except ValueError as exc:                   # an href leaving the package's nodes
            raise InputFileError(self.package.path, str(exc)) from None

    def _node(self, node_id: str) -> dict:
        doc = self.package.json(f"nodes/{node_id}/3dNodeIndexDocument")
        mbs = doc.get("mbs")
        if not (isinstance(mbs, list) and len(mbs) == 4 and all(isinstance(v, (int, float)) for v in mbs)):
            raise InputFileError(self.package.path, f"nodes/{node_id}: its mbs is not [x, y, z, radius]")
        node = {"index": node_id, "obb": {"center": mbs[:3]}, "radius": float(mbs[3]),
                "children": [_child(c, node_id, self.package) for c in doc.get("children") or []]}
        for selection in doc.get("lodSelection") or []:
            if isinstance(selection, dict) and selection.get("metricType") in ("maxScreenThreshold",
                                                                                 "maxScreenThresholdSQ"):
                node.update(lodThreshold=selection.get("maxError"), metric=selection["metricType"])
                break
        geometry = doc.get("geometryData") or []
        if geometry and isinstance(geometry[0], dict) and isinstance(geometry[0].get("href"), str):
            texture = (doc.get("textureData") or [{}])[0]
            node["mesh"] = {"geometry": {"href": _href(node_id, geometry[0]["href"])},
                            "material": {"href": _href(node_id, texture["href"])
                                         if isinstance(texture, dict) and isinstance(texture.get("href"), str)
                                         else None}}
        return node


def geometry_layouts(store: dict) -> list[dict]:
    """The buffer layouts the store's ``defaultGeometrySchema`` allows, as 1.7 geometry buffers:
    with its ``region`` attribute, then without it."""
    schema = store.get("defaultGeometrySchema") or {}
    layout = {"offset": 8}
    for group, order in (("vertexAttributes", "ordering"), ("featureAttributes", "featureAttributeOrder")):
        attributes = schema.get(group) or {}
        for name in schema.get(order) or []:
            field = attributes.get(name)
            if isinstance(field, dict):
                layout[_KEYS.get(name, name)] = {"type": field.get("valueType"),
                                                 "component": field.get("valuesPerElement", 1)}
    plain = {k: v for k, v in layout.items() if k != "uvRegion"}
    return [layout, plain] if "uvRegion" in layout else [layout]


def _child(child, parent: str, package: Package) -> str:
    if isinstance(child, dict) and isinstance(child.get("href"), str):
        return _href(parent, child["href"]).removeprefix("nodes/")
    if isinstance(child, dict) and isinstance(child.get("id"), str):
        return child["id"]
    raise InputFileError(package.path, f"nodes/{parent}: a child names no id nor href")


def _href(node_id: str, href: str) -> str:
    """An href of node ``node_id``'s document as an entry name (``./geometries/0`` ->
    ``nodes/<id>/geometries/0``), kept inside ``nodes/``."""
    name = posixpath.normpath(posixpath.join("nodes", node_id, href))
    if not name.startswith("nodes/") or ".." in name.split("/"):
        raise ValueError(f"href {href!r} of node {node_id} leaves the package's nodes")
    return name


def _folder(root: str) -> str:
    return root.removeprefix("nodes/")
