"""XML read as city-model tools read it: namespace defects are recovered from, nothing else is.

Real city files carry Application Domain Extension elements (PLATEAU's ``uro:``, the energy
ADE ...) and some of them use a prefix the file never declares
(``<energy:isHeated>`` without ``xmlns:energy``). libxml2 calls that a namespace error and,
when recovering, keeps the element under its prefixed name with no namespace; the tools of
the ecosystem (the PLATEAU SDK, citygml4j in lenient mode) read such files. A streaming
reader parses with ``recover=True`` and hands every parse event to :meth:`XmlDefects.check`:

* an error of libxml2's NAMESPACE domain (undeclared prefix, a namespace name that is not a
  URI) is remembered, and :meth:`XmlDefects.warn` names the file, the first line and the
  defect once per kind (per prefix for undeclared ones);
* any other error (a truncated file, mismatched tags, a stray ``&``, a redefined attribute)
  refuses the file with an InputFileError naming its line, as a parse without recovery would.

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


class XmlDefects:
    """The XML errors of one file over one or more streamed parses (see the module docstring)."""

    def __init__(self, path: Path):
        self.path = path
        self.first: dict[str, tuple[int, str]] = {}   # kind -> (line, libxml2's message) of its first case
        self.counts: Counter = Counter()
        self._seen = 0                                 # errors of the current parse already looked at
        self._lines: set[tuple[int, str]] = set()      # (line, message) already counted (a file read twice)

    def start(self) -> None:
        """A new parse of the file begins (its error log starts empty)."""
        self._seen = 0

    @property
    def recovered(self) -> bool:
        """Whether any namespace defect was recovered from (elements may carry prefixed names)."""
        return bool(self.first)

    def check(self, context) -> None:
        """Look at the errors ``context`` (an lxml iterparse) logged since the last call."""
        log = context.error_log
        if len(log) == self._seen:
            return
        for entry in list(log)[self._seen:]:
            if entry.domain_name != "NAMESPACE":
                raise InputFileError(self.path, f"malformed XML at line {entry.line}: {entry.message.strip()}")
            if (entry.line, entry.message) in self._lines:
                continue
            self._lines.add((entry.line, entry.message))
            match = _PREFIX.match(entry.message)
            kind = f"undeclared namespace prefix {match.group(1)}" if match else entry.type_name
            self.first.setdefault(kind, (entry.line, entry.message.strip()))
            self.counts[kind] += 1
        self._seen = len(log)

    def warn(self, stacklevel: int = 3) -> None:
        """One warning per kind of recovered defect: file, first line, libxml2's words, how many."""
        for kind, (line, message) in sorted(self.first.items()):
            more = self.counts[kind] - 1
            also = f"; {more} more like it" if more else ""
            warnings.warn(f"{self.path}: line {line}: {message} ({kind}: read on without "
                          f"its namespace{also})", stacklevel=stacklevel)


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
