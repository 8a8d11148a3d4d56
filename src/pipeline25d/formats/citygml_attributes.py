"""The attributes of one CityGML city object (1.0, 2.0, 3.0), read from its element before it is freed.

* Simple properties: every child element of the object that holds text and no elements
  (``gml:name``, ``gml:description``, ``bldg:measuredHeight``, ``bldg:storeysAboveGround``,
  ``bldg:function`` / ``usage`` / ``class``, ``bldg:yearOfConstruction``, ``bldg:roofType``, an
  ADE's simple properties ...), by local name; a name given twice (two ``bldg:function``) becomes
  a list. Numbers where CityGML types them as numbers (:data:`NUMERIC`); a ``uom`` other than
  metres is kept beside the value as ``<name>_uom``. CityGML 3.0's ``con:height`` is ``height``
  (a mapping: highReference, lowReference, status, value); a measured one in metres is also
  ``measuredHeight``, as 2.0 names it.
* Generic attributes: CityGML 1.0/2.0 ``gen:stringAttribute``, ``intAttribute``, ``doubleAttribute``,
  ``dateAttribute``, ``uriAttribute``, ``measureAttribute`` (``name`` attribute, ``gen:value``) and
  ``gen:genericAttributeSet`` (a mapping of its members); 3.0 ``genericAttribute`` holding
  ``gen:StringAttribute`` ... ``gen:CodeAttribute`` / ``gen:GenericAttributeSet`` (``gen:name``,
  ``gen:value``). Int and measure/double values are numbers, the others text.
* BuildingParts are folded into their building: the building is the object (its faces and its
  parts' faces share its id, as they are drawn) and each part's attributes are listed under the
  building's ``parts`` attribute, by the part's ``gml:id`` (``BuildingPart#n`` without one).

Nested structures other than these (addresses, external references) are not read.
"""

from __future__ import annotations

from pipeline25d.formats.attributes import Limiter, object_info

GML_ID = ("{http://www.opengis.net/gml}id", "{http://www.opengis.net/gml/3.2}id")
#: simple properties typed as numbers by CityGML
NUMERIC = frozenset({"measuredHeight", "storeysAboveGround", "storeysBelowGround", "yearOfConstruction",
                     "yearOfDemolition"})
_GENERIC_2 = {"stringAttribute": str, "intAttribute": int, "doubleAttribute": float, "dateAttribute": str,
              "uriAttribute": str, "measureAttribute": float}
_GENERIC_3 = {"StringAttribute": str, "IntAttribute": int, "DoubleAttribute": float, "DateAttribute": str,
              "UriAttribute": str, "MeasureAttribute": float, "CodeAttribute": str}
_METRES = frozenset({"m", "#m", "metre", "meter", "urn:ogc:def:uom:EPSG::9001", "urn:adv:uom:m"})
_PARTS = frozenset({"BuildingPart"})


def local_name(tag) -> str:
    """The element name without its namespace ("" for comments and processing instructions)."""
    return tag[tag.rfind("}") + 1:] if isinstance(tag, str) else ""


def city_object_info(elem, limiter: Limiter) -> dict:
    """``{"type", "attributes"}`` of the city object ``elem`` (:mod:`pipeline25d.formats.attributes`)."""
    attrs = _attributes(elem)
    parts = {}
    for n, part in enumerate(elem.iterdescendants(*(f"{{*}}{name}" for name in _PARTS))):
        key = part.get(GML_ID[0]) or part.get(GML_ID[1]) or f"{local_name(part.tag)}#{n}"
        parts[key] = _attributes(part)
    if parts and any(parts.values()):
        attrs["parts"] = parts
    return object_info(local_name(elem.tag), limiter.attributes(attrs))


def _attributes(elem) -> dict:
    out: dict = {}
    for child in elem:
        name = local_name(child.tag)
        if not name:
            continue
        if name in _GENERIC_2 or name == "genericAttributeSet":
            _add(out, *_generic_2(child))
        elif name == "height":
            _heights(child, out)
        elif name == "genericAttribute":
            for inner in child:
                if local_name(inner.tag):
                    _add(out, *_generic_3(inner))
        elif len(child) == 0 and (child.text or "").strip():
            value = _typed(child.text.strip(), float if name in NUMERIC else str)
            if name in ("storeysAboveGround", "storeysBelowGround", "yearOfConstruction", "yearOfDemolition") \
                    and isinstance(value, float) and value.is_integer():
                value = int(value)
            _add(out, name, value)
            uom = child.get("uom")
            if uom and uom not in _METRES:
                _add(out, f"{name}_uom", uom)
    return out


def _heights(prop, out: dict) -> None:
    """CityGML 3.0 ``con:height``: its ``con:Height`` (references, status, value) under ``height``; a
    measured one in metres is also ``measuredHeight`` (what 2.0 calls it), when the object has none."""
    for height in prop:
        if local_name(height.tag) != "Height":
            continue
        fields = {local_name(c.tag): (c.text or "").strip() for c in height if local_name(c.tag) and len(c) == 0}
        value = next((c for c in height if local_name(c.tag) == "value"), None)
        if "value" in fields:
            fields["value"] = _typed(fields["value"], float)
        _add(out, "height", fields)
        metres = value is None or value.get("uom") in (None, *_METRES)
        if fields.get("status") == "measured" and isinstance(fields.get("value"), float) and metres \
                and "measuredHeight" not in out:
            out["measuredHeight"] = fields["value"]


def _generic_2(elem) -> tuple[str, object]:
    """(name, value) of a CityGML 1.0/2.0 generic attribute or attribute set."""
    name = elem.get("name") or local_name(elem.tag)
    if local_name(elem.tag) == "genericAttributeSet":
        members: dict = {}
        for child in elem:
            if local_name(child.tag) in _GENERIC_2 or local_name(child.tag) == "genericAttributeSet":
                _add(members, *_generic_2(child))
        return name, members
    value = next((c.text for c in elem if local_name(c.tag) == "value"), None)
    return name, _typed((value or "").strip(), _GENERIC_2[local_name(elem.tag)])


def _generic_3(elem) -> tuple[str, object]:
    """(name, value) of a CityGML 3.0 generic attribute (``gen:StringAttribute`` ... ``GenericAttributeSet``)."""
    kind = local_name(elem.tag)
    name = next(((c.text or "").strip() for c in elem if local_name(c.tag) == "name"), "") or kind
    if kind == "GenericAttributeSet":
        members: dict = {}
        for child in elem:
            if local_name(child.tag) == "genericAttribute":
                for inner in child:
                    if local_name(inner.tag):
                        _add(members, *_generic_3(inner))
        return name, members
    value = next((c.text for c in elem if local_name(c.tag) == "value"), None)
    return name, _typed((value or "").strip(), _GENERIC_3.get(kind, str))


def _typed(text: str, kind: type):
    """``text`` as ``kind`` (int, float or str); the text itself when it is not such a number."""
    if kind is str:
        return text
    try:
        return int(text) if kind is int else float(text)
    except ValueError:
        return text


def _add(out: dict, name: str, value) -> None:
    """Set ``out[name]``; a name given again makes a list of its values (values read here are
    never lists themselves)."""
    if name not in out:
        out[name] = value
    elif isinstance(out[name], list):
        out[name].append(value)
    else:
        out[name] = [out[name], value]
