"""What a robot refuses to run: SPARQL Update (its KB is read-only) and
queries whose ``SERVICE`` or ``FROM`` would fetch from the network."""

from __future__ import annotations

import re

from .errors import KBError, QuerySyntaxError, UpdateRefused

# Each alternative of the prologue can match a given text in one way only,
# so a failing match cannot backtrack exponentially (queries come from the
# network).
_UPDATE_KEYWORD = re.compile(
    r"(?:\s|\#[^\n]*(?:\n|$)|(?:PREFIX|BASE)\b[^<]*<[^>]*>)*"
    r"(INSERT|DELETE|LOAD|CLEAR|CREATE|DROP|COPY|MOVE|ADD|WITH)\b",
    re.IGNORECASE,
)

_ANY_UPDATE_WORD = re.compile(r"\b(?:INSERT|DELETE|LOAD|CLEAR|CREATE|DROP|COPY|MOVE|ADD)\b", re.IGNORECASE)

_UPDATE_OPERATION_NAMES = {
    "InsertData": "INSERT DATA",
    "DeleteData": "DELETE DATA",
    "DeleteWhere": "DELETE WHERE",
    "Modify": "DELETE/INSERT",
    "Load": "LOAD",
    "Clear": "CLEAR",
    "Drop": "DROP",
    "Create": "CREATE",
    "Add": "ADD",
    "Move": "MOVE",
    "Copy": "COPY",
}


def _update_operations(text: str) -> tuple[str, ...] | None:
    """The operations of ``text`` if it is SPARQL Update, else None.

    Only called once a text has failed to parse as a query.  rdflib's update
    grammar only parses (nothing is executed); a text that starts like an
    update but does not parse as one still counts, so a malformed update
    gets "refused" rather than a confusing "expected SELECT" error.
    """
    from rdflib.plugins.sparql.parser import parseUpdate

    if _ANY_UPDATE_WORD.search(text) is None:
        return None  # spare pyparsing (~0.1 s on a long malformed query)
    try:
        parsed = parseUpdate(text)
    except Exception:  # noqa: BLE001 - broad on purpose: any failure means "not a valid update"
        parsed = None
    if parsed is not None and "request" in parsed:  # an empty update (prologue only) is no update
        ops = tuple(_UPDATE_OPERATION_NAMES.get(r.name, r.name.upper()) for r in parsed["request"])
        if ops:
            return ops
    m = _UPDATE_KEYWORD.match(text)
    return (m.group(1).upper(),) if m else None


def refuse_or_syntax(text: str, error: QuerySyntaxError) -> KBError:
    """For a text that failed to parse as a query: :class:`UpdateRefused`
    if it is SPARQL Update, else the backend's syntax ``error``."""
    ops = _update_operations(text)
    return UpdateRefused(ops) if ops else error


_TOKENS = re.compile(
    r'"""(?:[^"\\]|\\.|"(?!""))*"""'  # long strings
    r"|'''(?:[^'\\]|\\.|'(?!''))*'''"
    r'|"(?:[^"\\\n]|\\.)*"'  # short strings
    r"|'(?:[^'\\\n]|\\.)*'"
    r'|<[^<>"{}|^`\\\s]*>'  # IRIs
    r"|\#[^\n]*"  # comments
    r"|[?$]\w+"  # variables
    r"|(?<![\w:.-])(SERVICE|FROM)(?![\w:-])",  # the keywords, not in prefixed names
    re.IGNORECASE,
)


def refused_feature(text: str) -> str | None:
    """``SERVICE`` or ``FROM`` if the query uses it as a keyword (outside
    strings, IRIs, comments and names), else None.  A substring test first
    keeps the common case at ~1 us."""
    lowered = text.lower()
    if "service" not in lowered and "from" not in lowered:
        return None
    for m in _TOKENS.finditer(text):
        if m.group(1):
            return m.group(1).upper()
    return None

