"""XML read as city-model tools read it: namespace defects and stray characters outside the
geometry are recovered from, nothing else is.

Real city files carry Application Domain Extension elements (PLATEAU's ``uro:``, the energy
ADE ...) and some of them use a prefix the file never declares
(``<energy:isHeated>`` without ``xmlns:energy``). libxml2 calls that a namespace error and,
when recovering, keeps the element under its prefixed name with no namespace; the tools of
the ecosystem (the PLATEAU SDK, citygml4j in lenient mode) read such files. A streaming
reader parses with ``recover=True`` and hands every parse event to :meth:`XmlDefects.check`:

* an error of libxml2's NAMESPACE domain (undeclared prefix, a namespace name that is not a
  URI) is remembered, and :meth:`XmlDefects.warn` names the file, the first line and the
  defect once per kind (per prefix for undeclared ones);
* a stray character (a bare ``&``, an undefined entity such as ``&nbsp;``, a control
  character in text, ``<`` in an attribute value: recovery drops the character and changes no
  element) is placed by :meth:`XmlDefects.place` in the streamed element that holds its line:
  outside a geometry it is remembered and warned of like a namespace defect, naming line and
  element; inside one (the caller's ``in_geometry``) it refuses the file, since the coordinates
  it stands in can no longer be trusted;
* any other error (a truncated file, mismatched tags, a stray ``<`` in text, which makes
  libxml2 drop elements, a redefined attribute) refuses the file with an InputFileError naming
  its line, as a parse without recovery would.

The reader decides where a recovered element may stand: :func:`recovered_name` tells it an
element (or one of its attributes) kept its undeclared prefix, so it can refuse one inside
the geometry, where dropping it would lose or misplace triangles.
"""

from __future__ import annotations

import re
import warnings
from collections import Counter
from pathlib import Path

from pipeline25d.core.errors import InputFileError

_PREFIX = re.compile(r"Namespace prefix (\S+)")
#: libxml2 errors whose recovery drops characters and keeps every element -> how their message starts
_STRAY = {"ERR_NAME_REQUIRED": "xmlParseEntityRef", "ERR_ENTITYREF_SEMICOL_MISSING": "",
          "ERR_UNDECLARED_ENTITY": "", "ERR_INVALID_CHAR": "PCDATA invalid Char", "ERR_LT_IN_ATTRIBUTE": ""}


class XmlDefects:
    """The XML errors of one file over one or more streamed parses (see the module docstring)."""

    def __init__(self, path: Path):
        self.path = path
        self.first: dict[str, tuple[int, str]] = {}   # kind -> (line, libxml2's message) of its first case
        self.counts: Counter = Counter()
        self._seen = 0                                 # errors of the current parse already looked at
        self._lines: set[tuple[int, str]] = set()      # (line, message) already counted (a file read twice)
        self.pending: list[tuple[int, str]] = []       # stray characters not yet placed in an element
        self._tail: tuple[int, str, bool] | None = None   # last line, element, in a geometry of the last placed

    def start(self) -> None:
        """A new parse of the file begins (its error log starts empty)."""
        self._seen = 0
        self._tail = None

    @property
    def recovered(self) -> bool:
        """Whether any namespace defect was recovered from (elements may carry prefixed names)."""
        return any(not kind.startswith("stray") for kind in self.first)

    def check(self, context) -> None:
        """Look at the errors ``context`` (an lxml iterparse) logged since the last call."""
        log = context.error_log
        if len(log) == self._seen:
            return
        for entry in list(log)[self._seen:]:
            stray = entry.message.startswith(_STRAY.get(entry.type_name, "\0"))
            if entry.domain_name != "NAMESPACE" and not stray:
                raise InputFileError(self.path, f"malformed XML at line {entry.line}: {entry.message.strip()}")
            if (entry.line, entry.message) in self._lines:
                continue
            self._lines.add((entry.line, entry.message))
            if stray:
                self.pending.append((entry.line, entry.message.strip()))
                continue
            match = _PREFIX.match(entry.message)
            kind = f"undeclared namespace prefix {match.group(1)}" if match else entry.type_name
            self.first.setdefault(kind, (entry.line, entry.message.strip()))
            self.counts[kind] += 1
        self._seen = len(log)

    def place(self, elem, in_geometry) -> None:
        """Place the pending stray characters that lie in streamed element ``elem`` (None: the
        parse ended, all of them): recovered outside a geometry, an InputFileError inside one
        (``in_geometry(element)``). A character after the start line of an element's last
        descendant counts as that descendant's (its text may run on over lines), one before the
        first element as outside any."""
        if not self.pending:
            return
        first = elem.sourceline if elem is not None else None
        later = []
        for line, message in self.pending:
            if first is not None and line >= first:
                later.append((line, message))
                continue
            if self._tail is not None:
                self._recover(line, message, self._tail[1], self._tail[2])
            else:
                self._recover(line, message, None, False)
        self.pending = later
        if elem is None:
            return
        inside = [e for e in elem.iter() if isinstance(e.tag, str) and e.sourceline is not None]
        last = inside[-1]
        geometric = any(in_geometry(a) for a in (last, *last.iterancestors()))
        self._tail = (last.sourceline, _local(last.tag), geometric)
        keep = []
        for line, message in self.pending:
            if line > last.sourceline:
                keep.append((line, message))
                continue
            holder = [e for e in inside if e.sourceline <= line][-1]
            self._recover(line, message, _local(holder.tag),
                          any(in_geometry(a) for a in (holder, *holder.iterancestors())))
        self.pending = keep

    def _recover(self, line: int, message: str, element: str | None, geometric: bool) -> None:
        where = f"<{element}>" if element else "no city object"
        if geometric:
            raise InputFileError(self.path, f"malformed XML at line {line}: {message} in {where}, inside a geometry "
                                            "(its coordinates cannot be trusted)")
        kind = f"stray character in {where}"
        self.first.setdefault(kind, (line, message))
        self.counts[kind] += 1

    def warn(self, stacklevel: int = 3) -> None:
        """One warning per kind of recovered defect: file, first line, libxml2's words, how many."""
        for kind, (line, message) in sorted(self.first.items()):
            more = self.counts[kind] - 1
            also = f"; {more} more like it" if more else ""
            how = "dropped" if kind.startswith("stray") else "read on without its namespace"
            warnings.warn(f"{self.path}: line {line}: {message} ({kind}: {how}{also})", stacklevel=stacklevel)


def _local(tag: str) -> str:
    return tag[tag.rfind("}") + 1:]


def recovered_name(elem) -> str | None:
    """The prefixed name of ``elem`` or of one of its attributes when the parser kept it without
    a namespace (an undeclared prefix), else None."""
    tag = elem.tag
    if not isinstance(tag, str):
        return None
    if tag[:1] != "{" and ":" in tag:
        return f"<{tag}>"
    for key in elem.keys():
        if key[:1] != "{" and ":" in key:
            return f"attribute {key} of <{tag[tag.rfind('}') + 1:]}>"
    return None


def recovered_xml(data: bytes, path: Path, in_geometry) -> bytes:
    """``data`` as it is when it parses; else the document libxml2 recovers, when every defect
    is one :class:`XmlDefects` recovers from and lies outside a geometry (``in_geometry``), with
    one warning per kind. For readers that parse a whole document themselves (pycollada):
    they get the repaired bytes. External entities are never resolved, nothing is fetched."""
    from lxml import etree

    strict = etree.XMLParser(resolve_entities=False, no_network=True, huge_tree=True)
    try:
        etree.fromstring(data, strict)
        return data
    except etree.XMLSyntaxError:
        pass
    parser = etree.XMLParser(resolve_entities=False, no_network=True, huge_tree=True, recover=True)
    try:
        root = etree.fromstring(data, parser)
    except etree.XMLSyntaxError as exc:
        raise InputFileError(path, f"malformed XML at line {exc.lineno}: {exc.msg}") from None
    defects = XmlDefects(path)
    defects.check(parser)
    if root is None:
        raise InputFileError(path, "malformed XML: no document could be recovered")
    defects.place(root, in_geometry)
    defects.place(None, in_geometry)
    defects.warn(stacklevel=4)
    for entity in list(root.iter(etree.Entity)):   # an undefined entity is kept as a reference: drop it
        parent, tail = entity.getparent(), entity.tail or ""
        before = entity.getprevious()
        if before is not None:
            before.tail = (before.tail or "") + tail
        else:
            parent.text = (parent.text or "") + tail
        parent.remove(entity)
    return etree.tostring(root.getroottree(), xml_declaration=True, encoding="UTF-8")
