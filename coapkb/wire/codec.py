"""Result codecs: compact CBOR (content-format 60) and SPARQL 1.1 JSON (50).

Pure functions over :mod:`coapkb.model.results`.  Both codecs are *lossless*:
``decode(encode(r)) == r`` down to the exact lexical form, datatype and
language tag of every literal.  Decoders raise :class:`CodecError` and
nothing else on malformed input.

Compact CBOR is ``[vars, prefixes, rows]`` (SELECT), ``[null, prefixes,
triples]`` (CONSTRUCT, DESCRIBE) or a bool (ASK), with a ``true`` fourth
element when truncated and optionally wrapped in a stringref namespace; a
term is a native CBOR item only when the decoder's rendering
(:func:`render_double`, :func:`render_decimal`) gives its lexical form back
exactly, else an explicit array.  The structure is specified in
``docs/compact-results.cddl``, the semantics, examples, sizes and the
alternatives considered in ``docs/compact-results.md``.

The encoder is hand-written rather than built on ``cbor2.dumps`` (cbor2
costs about 1 us per nested array, and writing bytes directly controls
preferred serialisation and stringref numbering); decoding uses cbor2 (C),
restricted to the tags the format allows.
"""

from __future__ import annotations

import io
import json
import math
import re
import struct
from collections.abc import Iterable, Sequence
from typing import Any, Final, cast

import cbor2
from rdflib.term import BNode, Literal, URIRef

from ..errors import CoapkbError
from ..model.results import AskResult, GraphResult, QueryResult, SelectResult, Term, Triple

__all__ = [
    "CodecError",
    "WELL_KNOWN_DATATYPES",
    "GRAPH_VARS",
    "MAX_DECIMAL_SCALE",
    "MAX_PREFIX_TABLE_CHARS",
    "encode_cbor",
    "decode_cbor",
    "encode_json",
    "decode_json",
    "render_double",
    "render_decimal",
]


class CodecError(CoapkbError, ValueError):
    """Input that is not a valid encoding, or a result that cannot be encoded."""


_XSD: Final = "http://www.w3.org/2001/XMLSchema#"
_RDF: Final = "http://www.w3.org/1999/02/22-rdf-syntax-ns#"

# RDF 1.1 Concepts section 5.1, in its table's order.
_XSD_NAMES: Final = (
    "string", "boolean", "decimal", "integer",  # 0-3: core types
    "double", "float",  # 4-5
    "date", "time", "dateTime", "dateTimeStamp",  # 6-9
    "gYear", "gMonth", "gDay", "gYearMonth", "gMonthDay",  # 10-14
    "duration", "yearMonthDuration", "dayTimeDuration",  # 15-17
    "byte", "short", "int", "long",  # 18-21
    "unsignedByte", "unsignedShort", "unsignedInt", "unsignedLong",  # 22-25
    "positiveInteger", "nonNegativeInteger", "negativeInteger", "nonPositiveInteger",  # 26-29
    "hexBinary", "base64Binary",  # 30-31
    "anyURI", "language", "normalizedString", "token", "NMTOKEN", "Name", "NCName",  # 32-38
)  # fmt: skip
#: Datatypes addressed by a small integer code instead of through the prefix
#: table (``WELL_KNOWN_DATATYPES[code]``): the RDF 1.1 Concepts (section 5.1)
#: RDF-compatible XSD types in that table's order, then rdf:HTML and
#: rdf:XMLLiteral.  Codes 0-23 take one byte.  Part of the wire format:
#: append only, never reorder.
WELL_KNOWN_DATATYPES: Final[tuple[str, ...]] = (
    *(_XSD + name for name in _XSD_NAMES),
    _RDF + "HTML",  # 39
    _RDF + "XMLLiteral",  # 40
)
_DATATYPE_CODE: Final[dict[str, int]] = {iri: code for code, iri in enumerate(WELL_KNOWN_DATATYPES)}
_DT_BOOLEAN, _DT_DECIMAL, _DT_INTEGER, _DT_DOUBLE = (URIRef(WELL_KNOWN_DATATYPES[i]) for i in range(1, 5))
_DT_LANGSTRING: Final = _RDF + "langString"

#: The variables under which a graph result (CONSTRUCT/DESCRIBE) is written
#: as SPARQL-JSON bindings.
GRAPH_VARS: Final[tuple[str, str, str]] = ("subject", "predicate", "object")

#: Largest number of fractional digits a native decimal (tag 4) may carry:
#: bounds the text a decoder renders from a tiny input.  Longer fractions use
#: the explicit ``[lexical, 2]`` form.
MAX_DECIMAL_SCALE: Final = 1000

#: Largest total length of the resolved prefix table a decoder accepts
#: (namespaces are short; a cap keeps chained entries from amplifying input).
MAX_PREFIX_TABLE_CHARS: Final = 8192

_INT_MIN: Final = -(2**64)  # the range of CBOR major types 0 and 1
_INT_MAX: Final = 2**64 - 1

_ABSENT: Final = object()  # marks a missing JSON member


# --------------------------------------------------------------------------
# Lexical renderings shared by encoder and decoder
# --------------------------------------------------------------------------


def render_double(value: float) -> str:
    """The lexical form a decoder gives a native CBOR float (xsd:double).

    The shortest decimal that round-trips to the same binary64 value,
    written as Python's ``repr`` writes it: with decpt the position of the
    decimal point relative to the first significant digit (value =
    0.d1d2...dn x 10**decpt), plain notation when -4 < decpt <= 16, with
    ``.0`` added to a whole number (``"2.0"``, ``"0.001"``, ``"-0.0"``),
    else ``d1[.d2...dn]e<sign><at least two digits>`` (``"1e+16"``,
    ``"1.5e-07"``).  Not-a-number and the infinities use the XSD spellings
    ``NaN``, ``INF`` and ``-INF``.  This is the form rdflib gives every
    double it normalises, so doubles from either KB backend travel as
    3-9 byte floats; any other spelling ("1E0", "2") keeps its lexical form.
    """
    if value != value:
        return "NaN"
    if value == math.inf:
        return "INF"
    if value == -math.inf:
        return "-INF"
    return repr(value)


def render_decimal(exponent: int, mantissa: int) -> str:
    """The lexical form of the decimal fraction ``mantissa * 10**exponent``.

    ``exponent`` is <= 0 and gives the exact number of fractional digits,
    so ``4([-2, 150])`` is ``"1.50"`` and ``4([0, 7])`` is ``"7"``: trailing
    zeros survive, unlike a conversion through a number type.
    """
    digits = str(abs(mantissa))
    if exponent:
        scale = -exponent
        digits = digits.rjust(scale + 1, "0")
        digits = digits[:-scale] + "." + digits[-scale:]
    return "-" + digits if mantissa < 0 else digits


def _native_integer(lexical: str) -> int | None:
    """The CBOR integer for a canonical xsd:integer lexical form, else None."""
    if len(lexical) > 21:  # longer than any 64-bit value; also keeps int() cheap
        return None
    try:
        value = int(lexical)
    except ValueError:
        return None
    if str(value) != lexical or not _INT_MIN <= value <= _INT_MAX:
        return None  # "01", "+1", "-0", " 1", "1_0", non-ASCII digits, too big
    return value


def _native_decimal(lexical: str) -> tuple[int, int] | None:
    """``(exponent, mantissa)`` when :func:`render_decimal` gives ``lexical`` back."""
    int_part, point, frac_part = lexical.partition(".")
    digits = int_part + frac_part
    if len(int_part) > 21 or len(frac_part) > MAX_DECIMAL_SCALE:
        return None
    try:
        mantissa = int(digits)
    except ValueError:
        return None
    if len(digits) > 19 and not _INT_MIN <= mantissa <= _INT_MAX:
        return None
    exponent = -len(frac_part)
    # Fast path: the digits are already canonical ("129.99", "-1.5", "7"), so
    # render_decimal would rebuild exactly ``lexical``; it settles the rest
    # ("0.05" is fine; "-0.0", "007", "1.", "+1.5", ".5", " 1.5" are not).
    if str(mantissa) == digits and int_part not in ("", "-") and (frac_part or not point):
        return exponent, mantissa
    if render_decimal(exponent, mantissa) != lexical:
        return None
    return exponent, mantissa


def _native_double(lexical: str) -> float | None:
    """The float whose :func:`render_double` is exactly ``lexical``, else None."""
    if len(lexical) > 32:  # render_double never produces more than 24 characters
        return None
    try:
        value = float(lexical)
    except ValueError:
        return None
    return value if render_double(value) == lexical else None


class _DecimalFraction:
    """A tag-4 decimal fraction as it travels: exponent and mantissa."""

    __slots__ = ("exponent", "mantissa")

    def __init__(self, exponent: Any, mantissa: Any) -> None:
        self.exponent = exponent
        self.mantissa = mantissa


# --------------------------------------------------------------------------
# CBOR encoding
# --------------------------------------------------------------------------

_BYTE: Final = tuple(bytes((i,)) for i in range(256))
_STRINGREF_NAMESPACE: Final = b"\xd9\x01\x00"  # tag 256
_TRUE, _FALSE, _NULL = b"\xf5", b"\xf4", b"\xf6"


_PACK_8: Final = struct.Struct(">BB").pack
_PACK_16: Final = struct.Struct(">BH").pack
_PACK_32: Final = struct.Struct(">BI").pack
_PACK_64: Final = struct.Struct(">BQ").pack


def _head(major: int, n: int) -> bytes:
    """The initial byte(s) of a data item: ``major`` is the type's top 3 bits."""
    if n < 24:
        return _BYTE[major | n]
    if n < 0x100:
        return _PACK_8(major | 24, n)
    if n < 0x10000:
        return _PACK_16(major | 25, n)
    if n < 0x100000000:
        return _PACK_32(major | 26, n)
    return _PACK_64(major | 27, n)


def _int_bytes(n: int) -> bytes:
    if 0 <= n < 24:
        return _BYTE[n]
    if -24 <= n < 0:
        return _BYTE[0x1F - n]  # major type 1 carries -1 - n
    return _head(0x00, n) if n >= 0 else _head(0x20, -1 - n)


def _float_bytes(value: float) -> bytes:
    """Preferred serialisation (RFC 8949 4.1): the shortest exact width."""
    if value != value:
        return b"\xf9\x7e\x00"
    for prefix, fmt in ((b"\xf9", ">e"), (b"\xfa", ">f")):
        try:
            packed = struct.pack(fmt, value)
        except OverflowError:
            continue
        if struct.unpack(fmt, packed)[0] == value:
            return prefix + packed
    return b"\xfb" + struct.pack(">d", value)


def _stringref_min_length(index: int) -> int:
    """Shortest string the stringref spec numbers when ``index`` is next."""
    if index < 24:
        return 3
    if index < 0x100:
        return 4
    if index < 0x10000:
        return 5
    if index < 0x100000000:
        return 7
    return 11


# Datatypes with a native CBOR form: 1 boolean, 2 decimal, 3 integer, 4 double.
_NATIVE_KIND: Final = {WELL_KNOWN_DATATYPES[code]: code for code in (1, 2, 3, 4)}


def _check_vars(variables: Sequence[str]) -> None:
    for name in variables:
        if not isinstance(name, str):
            raise CodecError(f"variable name must be a string, got {name!r}")
    if len(set(variables)) != len(variables):
        raise CodecError(f"duplicate variable names in {list(variables)!r}")


def _check_triple(triple: Sequence[object], where: str) -> Triple:
    """RDF well-formedness: both codecs refuse what the other could not carry.
    Returns the three terms, typed."""
    if len(triple) != 3:
        raise CodecError(f"{where}: a triple needs 3 terms, got {len(triple)}")
    subject, predicate, obj = triple
    if not isinstance(subject, (URIRef, BNode)):
        raise CodecError(f"{where}: subject must be an IRI or blank node, got {subject!r}")
    if not isinstance(predicate, URIRef):
        raise CodecError(f"{where}: predicate must be an IRI, got {predicate!r}")
    if not isinstance(obj, (URIRef, BNode, Literal)):
        raise CodecError(f"{where}: object must be an RDF term, got {obj!r}")
    return subject, predicate, obj


def _pays_off(prefix: str, uses: int) -> bool:
    """Whether a table entry for ``prefix`` saves bytes over sending it inline.

    The entry costs its own text once and saves that text on every use, so
    any non-trivial prefix pays off from its second use.
    """
    size = len(prefix.encode())
    return size > 0 and (uses - 1) * size > len(_head(0x60, size))


class _Plan:
    """Pass 1's findings: how to split each IRI, and the prefix table.

    ``splits`` maps an IRI to its namespace split (last '#' or '/');
    ``suffix_splits`` to a longer prefix whose local part is another string
    of the same row (``...#Shape_`` + ``"Gucci_bag_14"``), used when that
    prefix made it into the table, so the local part becomes a stringref.
    ``entries`` is the prefix table as sent: absolute text, or
    ``(base, suffix)`` for an entry extending an earlier one.
    """

    __slots__ = ("splits", "suffix_splits", "prefixes", "entries")

    def __init__(
        self,
        splits: dict[str, tuple[str, str]],
        suffix_splits: dict[str, tuple[str, str]],
        prefixes: list[str],
    ) -> None:
        self.splits = splits
        self.suffix_splits = suffix_splits
        self.prefixes = prefixes
        self.entries: list[str | tuple[int, str]] = []
        for i, prefix in enumerate(prefixes):
            entry: str | tuple[int, str] = prefix
            best = len(_head(0x60, len(prefix.encode()))) + len(prefix.encode())
            for j in range(i):
                base = prefixes[j]
                if base and len(base) < len(prefix) and prefix.startswith(base):
                    suffix = prefix[len(base) :].encode()
                    cost = 1 + len(_int_bytes(j)) + len(_head(0x60, len(suffix))) + len(suffix)
                    if cost < best:
                        entry, best = (j, prefix[len(base) :]), cost
            self.entries.append(entry)


def _split_iri(iri: str) -> tuple[str, str]:
    """Namespace and local name: split after the last '#' or '/'."""
    cut = max(iri.rfind("#"), iri.rfind("/")) + 1
    return iri[:cut], iri[cut:]


def _row_string(term: object, splits: dict[str, tuple[str, str]]) -> str | None:
    """The text a stringref could share: a plain literal, or an IRI's local name.

    Exact type tests come first: rdflib terms are ABCs, and a failing
    ``isinstance`` on them costs ten times a passing one.
    """
    kind = type(term)
    if kind is URIRef or (kind is not Literal and term is not None and isinstance(term, URIRef)):
        iri = str(term)
        return (splits.get(iri) or _split_iri(iri))[1]
    if kind is Literal or (term is not None and isinstance(term, Literal)):
        literal = cast(Literal, term)
        return str(literal) if literal._datatype is None and literal._language is None else None
    return None


def _suffix_columns(sample: Sequence[Sequence[object]], splits: dict[str, tuple[str, str]]) -> list[tuple[int, int]]:
    """Column pairs ``(j, k)`` where column j's IRI local name ends with column k's string.

    Found on a few sample rows, then tested on every row: in a SELECT (or
    CONSTRUCT) result such relations hold by column, and testing a known
    pair is much cheaper than searching every row.
    """
    pairs: list[tuple[int, int]] = []
    for row in sample:
        strings = [_row_string(term, splits) for term in row]
        ends = tuple(s for s in strings if s is not None and len(s) >= 3)
        if not ends:
            continue
        for j, term in enumerate(row):
            local = strings[j]
            # A proper suffix of local is a suffix of local[1:]: one C call
            # rules out the common case of no match.
            if local is None or type(term) is Literal or not local[1:].endswith(ends):
                continue  # (a plain literal's text is no IRI local name)
            for k, s in enumerate(strings):
                if k != j and s and 3 <= len(s) < len(local) and local.endswith(s) and (j, k) not in pairs:
                    pairs.append((j, k))
    return pairs


def _count_iris(rows: Sequence[Sequence[object]], datatypes: bool, splits: dict[str, tuple[str, str]]) -> dict[str, int]:
    """How often each IRI is used (also each custom datatype's, with
    ``datatypes``), splitting every new IRI into ``splits``."""
    iri_uses: dict[str, int] = {}
    last = "\0"  # namespace of the previous new IRI ("\0" starts no IRI)

    def split_of(iri: str) -> tuple[str, str]:
        nonlocal last
        # Split at the last '#' or '/'; most IRIs share the previous one's
        # namespace, which is cheaper to test than to search.
        local = iri[len(last) :]
        if iri.startswith(last) and "/" not in local and "#" not in local:
            split = (last, local)
        else:
            split = _split_iri(iri)
            last = split[0]
        splits[iri] = split
        return split

    for row in rows:
        for term in row:
            kind = type(term)
            if kind is Literal:
                if not datatypes:
                    continue
            elif kind is not URIRef:  # None, blank nodes, subclasses
                if term is None or kind is BNode:
                    continue
                if isinstance(term, Literal):
                    kind = Literal
                elif isinstance(term, URIRef):
                    kind = URIRef
                else:
                    continue
            if kind is URIRef:
                iri = str(term)
                if iri not in splits:
                    split_of(iri)
                iri_uses[iri] = iri_uses.get(iri, 0) + 1
            elif datatypes:
                datatype = cast(Literal, term).datatype
                if datatype is not None and str(datatype) not in _DATATYPE_CODE:
                    iri = str(datatype)
                    if iri not in splits:
                        split_of(iri)
                    iri_uses[iri] = iri_uses.get(iri, 0) + 1
    return iri_uses


def _row_suffix_splits(
    rows: Sequence[Sequence[object]], pairs: list[tuple[int, int]], splits: dict[str, tuple[str, str]]
) -> dict[str, tuple[str, str]]:
    """The longer prefix each IRI of column j could have in front of the
    string in column k of its row, for the column ``pairs``: the first
    row and pair that offer one settle it."""
    suffix_splits: dict[str, tuple[str, str]] = {}
    for row in rows:
        for j, k in pairs:
            term = row[j]
            if type(term) is not URIRef and (term is None or type(term) is Literal or not isinstance(term, URIRef)):
                continue
            iri = str(term)
            if iri in suffix_splits:
                continue
            other = row[k]
            if type(other) is Literal:  # inlined _row_string: the common cases first
                shared = str(other) if other._datatype is None and other._language is None else None
            else:
                shared = _row_string(other, splits)
            local = splits[iri][1]
            if shared and 3 <= len(shared) < len(local) and local.endswith(shared):
                suffix_splits[iri] = (iri[: -len(shared)], shared)
    return suffix_splits


def _paying_suffix_splits(
    suffix_splits: dict[str, tuple[str, str]], iri_uses: dict[str, int]
) -> dict[str, tuple[str, str]]:
    """The suffix splits whose longer prefix pays off, counting all its IRIs' uses."""
    suffix_uses: dict[str, int] = {}
    for iri, (prefix, _) in suffix_splits.items():
        suffix_uses[prefix] = suffix_uses.get(prefix, 0) + iri_uses[iri]
    accepted = {prefix for prefix, count in suffix_uses.items() if _pays_off(prefix, count)}
    return {iri: split for iri, split in suffix_splits.items() if split[0] in accepted}


def _chosen_prefix_table(
    iri_uses: dict[str, int], splits: dict[str, tuple[str, str]], suffix_splits: dict[str, tuple[str, str]]
) -> list[str]:
    """The prefixes that pay off, and ``""`` if any IRI is left without one,
    most used first, ties shortest first, then in order of first appearance."""
    uses: dict[str, int] = {}
    for iri, count in iri_uses.items():
        prefix = (suffix_splits.get(iri) or splits[iri])[0]
        uses[prefix] = uses.get(prefix, 0) + count
    table = [prefix for prefix, count in uses.items() if _pays_off(prefix, count)]
    unprefixed = sum(uses.values()) - sum(uses[prefix] for prefix in table)
    if unprefixed:
        table.append("")
        uses[""] = unprefixed
    order = {prefix: i for i, prefix in enumerate(table)}
    table.sort(key=lambda prefix: (-uses[prefix], len(prefix), order[prefix]))
    return table


def _capped_prefix_table(
    table: list[str], splits: dict[str, tuple[str, str]], suffix_splits: dict[str, tuple[str, str]]
) -> tuple[list[str], dict[str, tuple[str, str]]]:
    """The table's first entries that fit :data:`MAX_PREFIX_TABLE_CHARS`, the
    suffix splits still covered, and ``""`` for the IRIs left without a prefix."""
    kept: list[str] = []
    total = 0
    for prefix in table:
        if total + len(prefix) <= MAX_PREFIX_TABLE_CHARS:
            kept.append(prefix)
            total += len(prefix)
    suffix_splits = {iri: split for iri, split in suffix_splits.items() if split[0] in kept}
    if "" not in kept and any(split[0] not in kept and iri not in suffix_splits for iri, split in splits.items()):
        kept.append("")
    return kept, suffix_splits


def _plan(rows: Sequence[Sequence[object]], datatypes: bool) -> _Plan:
    """Pass 1: split the IRIs present and choose the prefix table.

    Entries are ordered by use count, most used first (one-byte indexes),
    ties shortest first (so longer prefixes can extend them), then in order
    of first appearance: the output is deterministic.  IRIs whose prefix
    has no entry share one ``""`` entry and travel whole.

    In results of several rows, an IRI whose local name ends with another
    string of its row (a plain literal or another IRI's local name, at least
    3 characters) is also offered the longer prefix in front of that string:
    the warehouse KB's ``Shape_Gucci_bag_14`` next to ``Gucci_bag_14``
    becomes ``[p, "Gucci_bag_14"]`` with ``p`` = ``...#Shape_``, and the
    local part a stringref, when that prefix pays off.

    Datatype IRIs outside :data:`WELL_KNOWN_DATATYPES` need entries too but
    are rare; scanning every literal for them is left to a second try
    (``datatypes=True``) when the emitter meets one.
    """
    splits: dict[str, tuple[str, str]] = {}
    # A row-specific prefix pays off only on repeats: look in results of
    # several rows, for column pairs found in the first two.
    pairs = _suffix_columns(rows[:2], splits) if len(rows) > 1 else []
    iri_uses = _count_iris(rows, datatypes, splits)
    suffix_splits = _paying_suffix_splits(_row_suffix_splits(rows, pairs, splits), iri_uses)
    table = _chosen_prefix_table(iri_uses, splits, suffix_splits)
    if sum(map(len, table)) > MAX_PREFIX_TABLE_CHARS:  # rare: keep what decoders accept
        table, suffix_splits = _capped_prefix_table(table, splits, suffix_splits)
    return _Plan(splits, suffix_splits, table)


class _MissingPrefix(Exception):
    """Pass 2 met a custom datatype that pass 1 did not count."""


class _Emitter:
    """Pass 2's state: the bytes so far, the stringref table and what its refs saved.

    With ``use_refs`` every text string goes through the stringref table
    (numbered exactly as a stringref decoder numbers them) and a repeat is
    sent as ``25(index)``.  Python call overhead (~0.1 us a call) dominates
    the encode time, so the row loop tests term kinds inline and a literal's
    every form is written by one call.
    """

    __slots__ = ("out", "write", "splits", "suffix_splits", "index", "empty", "use_refs", "refs", "saved", "next_min")

    def __init__(self, plan: _Plan, use_refs: bool) -> None:
        self.out = bytearray()
        self.write = self.out.extend
        self.splits, self.suffix_splits = plan.splits, plan.suffix_splits
        self.index = {prefix: i for i, prefix in enumerate(plan.prefixes)}
        # _plan adds "" when any IRI needs it.
        self.empty = _int_bytes(self.index[""]) if "" in self.index else b""
        self.use_refs = use_refs
        self.refs: dict[str, int] = {}
        self.saved = 0
        self.next_min = 3 if use_refs else 1 << 62  # shortest string the next ref index may number

    def text(self, s: str) -> None:
        """A text string, or a stringref to an earlier copy of it."""
        data = s.encode()
        n = len(data)
        if n >= 3 and self.use_refs:
            refs = self.refs
            ref_index = refs.get(s)
            if ref_index is not None:
                ref = b"\xd8\x19" + _int_bytes(ref_index)
                self.write(ref)
                self.saved += n + (1 if n < 24 else len(_head(0x60, n))) - len(ref)
                return
            if n >= self.next_min:
                refs[s] = len(refs)
                self.next_min = _stringref_min_length(len(refs))
        self.write(_BYTE[0x60 | n] if n < 24 else _head(0x60, n))
        self.write(data)

    def iri(self, value: str, head: bytes) -> None:
        """``head`` then the prefix index and local name (or "" entry, whole IRI)."""
        prefix, local = self.suffix_splits.get(value) or self.splits[value]
        i = self.index.get(prefix)
        if i is None:
            if not self.empty:
                raise AssertionError(f"prefix table does not cover {value!r}")
            self.write(head + self.empty)
            self.text(value)
        else:
            self.write(head + (_BYTE[i] if i < 24 else _int_bytes(i)))
            self.text(local)

    def header(self, variables: Sequence[str] | None, entries: Sequence[str | tuple[int, str]]) -> None:
        """The variable names (``null`` for a graph) and the prefix table."""
        if variables is None:
            self.write(_NULL)
        else:
            self.write(_head(0x80, len(variables)))
            for name in variables:
                self.text(name)
        self.write(_head(0x80, len(entries)))
        for entry in entries:
            if isinstance(entry, str):
                self.text(entry)
            else:  # [base, suffix]: extends an earlier entry
                self.write(b"\x82" + _int_bytes(entry[0]))
                self.text(entry[1])

    def rows(self, rows: Sequence[Sequence[Term | None]], width: int) -> None:
        """The rows (or triples), each an array of ``width`` terms."""
        write, text, iri, literal = self.write, self.text, self.iri, self.literal
        write(_head(0x80, len(rows)))
        row_head = _head(0x80, width)
        for row in rows:
            write(row_head)
            for term in row:
                # Exact type tests first: a failing isinstance on rdflib's
                # ABC-registered terms costs ten times a passing one.
                kind = type(term)
                if kind is Literal:
                    literal(term)  # type: ignore[arg-type]  # kind is type(term), taken once a term; mypy does not narrow through it
                elif kind is URIRef:
                    iri(str(term), b"\x82")
                elif term is None:
                    write(_NULL)
                elif kind is BNode:
                    write(b"\x81")
                    text(str(term))
                elif isinstance(term, Literal):
                    literal(term)
                elif isinstance(term, URIRef):
                    iri(str(term), b"\x82")
                elif isinstance(term, BNode):
                    write(b"\x81")
                    text(str(term))
                else:
                    raise CodecError(f"not an RDF term: {term!r}")

    def literal(self, literal: Literal) -> None:
        """A literal: plain text, ``[lexical, language]``, a native item,
        ``[lexical, code]`` or ``[lexical, prefix index, local name]``."""
        lexical = str(literal)
        datatype = literal._datatype  # the slot behind .datatype: 50 ns less a literal
        if datatype is None:
            language = literal._language
            if language is not None:
                self.write(b"\x82")
                self.text(lexical)
                self.text(language)
            else:
                self.text(lexical)
            return
        datatype_iri = str(datatype)
        native = _NATIVE_KIND.get(datatype_iri)
        if native is not None:  # a native item when the decoder's rendering gives lexical back
            if native == 2:
                fraction = _native_decimal(lexical)
                if fraction is not None:
                    exponent, mantissa = fraction  # tag 4, array of 2, exponent, mantissa
                    exponent_bytes = _BYTE[0x1F - exponent] if -24 <= exponent < 0 else _int_bytes(exponent)
                    self.write(b"\xc4\x82" + exponent_bytes + _int_bytes(mantissa))
                    return
            elif native == 1:
                if lexical == "true":
                    self.write(_TRUE)
                    return
                if lexical == "false":
                    self.write(_FALSE)
                    return
            elif native == 3:
                integer = _native_integer(lexical)
                if integer is not None:
                    self.write(_int_bytes(integer))
                    return
            else:
                double = _native_double(lexical)
                if double is not None:
                    self.write(_float_bytes(double))
                    return
        code = _DATATYPE_CODE.get(datatype_iri)
        if code is not None:  # [lexical, code]
            self.write(b"\x82")
            self.text(lexical)
            self.write(_int_bytes(code))
            return
        split = self.splits.get(datatype_iri)
        if split is None or (split[0] not in self.index and "" not in self.index):
            raise _MissingPrefix(datatype_iri)
        self.write(b"\x83")  # [lexical, prefix index, local name]
        self.text(lexical)
        self.iri(datatype_iri, b"")


def _emit(
    variables: Sequence[str] | None,
    plan: _Plan,
    rows: Sequence[Sequence[Term | None]],
    truncated: bool,
    use_refs: bool,
) -> tuple[bytearray, int]:
    """Pass 2: the CBOR bytes (without tag 256), and the bytes refs saved."""
    emitter = _Emitter(plan, use_refs)
    emitter.write(_head(0x80, 4 if truncated else 3))
    emitter.header(variables, plan.entries)
    emitter.rows(rows, 3 if variables is None else len(variables))
    if truncated:
        emitter.write(_TRUE)
    return emitter.out, emitter.saved


def encode_cbor(result: QueryResult) -> bytes:
    """Encode a result as compact CBOR (see ``docs/compact-results.md``).

    Deterministic: the same result always gives the same bytes.  The
    stringref namespace (tag 256) is used only when its references save
    more than the three bytes the tag costs.
    """
    if isinstance(result, AskResult):
        if not isinstance(result.value, bool):
            raise CodecError(f"ASK value must be a bool, got {result.value!r}")
        return _TRUE if result.value else _FALSE
    variables: Sequence[str] | None
    if isinstance(result, SelectResult):
        variables = result.variables
        _check_vars(variables)
        rows: Sequence[Sequence[Term | None]] = result.rows
    elif isinstance(result, GraphResult):
        variables = None
        rows = result.triples
        for i, triple in enumerate(rows):
            _check_triple(triple, f"triple {i}")
    else:
        raise CodecError(f"not a query result: {result!r}")
    truncated = bool(result.truncated)
    try:
        plan = _plan(rows, datatypes=False)
        try:
            body, saved = _emit(variables, plan, rows, truncated, use_refs=True)
        except _MissingPrefix:
            plan = _plan(rows, datatypes=True)
            body, saved = _emit(variables, plan, rows, truncated, use_refs=True)
        if saved > len(_STRINGREF_NAMESPACE):
            return _STRINGREF_NAMESPACE + body
        if saved:  # refs were used but save less than tag 256 costs
            body, _ = _emit(variables, plan, rows, truncated, use_refs=False)
    except UnicodeEncodeError as exc:
        raise CodecError(f"text is not encodable as UTF-8: {exc}") from exc
    return bytes(body)


# --------------------------------------------------------------------------
# CBOR decoding
# --------------------------------------------------------------------------


def _reject_tag(tag: int) -> Any:
    def reject(value: object, immutable: bool) -> object:
        raise CodecError(f"CBOR tag {tag} is not part of the compact results format")

    return reject


def _decimal_fraction(value: object, immutable: bool) -> object:
    if type(value) is not list or len(value) != 2:
        raise CodecError("tag 4 (decimal fraction) must hold [exponent, mantissa]")
    return _DecimalFraction(value[0], value[1])


#: Tags cbor2 would otherwise turn silently into Python values the format
#: does not allow (bignums, bigfloats, shared values, ...): rejected, so the
#: decoder accepts what the CDDL accepts.  Unknown tags come back as CBORTag
#: and are rejected as terms.  Tags 25/256 (stringref) are decoded by cbor2.
_SEMANTIC_DECODERS: Final = {
    4: _decimal_fraction,
    **{
        tag: _reject_tag(tag)
        for tag in (0, 1, 2, 3, 5, 28, 29, 30, 35, 36, 37, 52, 54, 100, 258, 260, 261, 1004, 55799)
    },
}
_MAX_DEPTH: Final = 16  # the format nests at most 6 deep


class _TermDecoder:
    """Turns decoded CBOR items into rdflib terms for one payload.

    rdflib's Literal constructor costs several microseconds, so equal items
    within one payload share one term object (terms are immutable).  Cache
    keys carry the item's shape, so ``[1, "a"]`` and ``[true, "a"]`` (equal
    in Python) never share an entry.
    """

    __slots__ = ("prefixes", "cache")

    def __init__(self, prefixes: list[str]) -> None:
        self.prefixes = prefixes
        self.cache: dict[tuple[object, ...], Term] = {}

    def term(self, item: object) -> Term:
        kind = type(item)
        key: tuple[object, ...]
        if kind is str:
            key = ("s", item)
        elif kind is int:
            key = ("i", item)
        elif kind is list:
            items = cast("list[object]", item)
            key = ("l", *map(type, items), *items)
            try:
                hash(key)
            except TypeError:
                raise CodecError(f"malformed term {item!r}") from None
        else:
            return self._build(item)
        cached = self.cache.get(key)
        if cached is None:
            cached = self.cache[key] = self._build(item)
        return cached

    def iri(self, index: object, local: object) -> URIRef:
        if type(index) is not int or type(local) is not str:
            raise CodecError(f"IRI must be [prefix index, local name], got {[index, local]!r}")
        if not 0 <= index < len(self.prefixes):
            raise CodecError(f"prefix index {index} out of range (table has {len(self.prefixes)} entries)")
        return URIRef(self.prefixes[index] + local)

    def _build(self, item: object) -> Term:
        kind = type(item)
        if kind is str:
            # normalize=False: a plain literal's lexical form is its value
            # already, and rdflib's normalising would only cost its time.
            return Literal(item, normalize=False)
        if kind is bool:
            return Literal("true" if item else "false", datatype=_DT_BOOLEAN, normalize=False)
        if kind is int:
            return Literal(str(item), datatype=_DT_INTEGER, normalize=False)
        if type(item) is float:
            return Literal(render_double(item), datatype=_DT_DOUBLE, normalize=False)
        if type(item) is _DecimalFraction:
            exponent, mantissa = item.exponent, item.mantissa
            if type(exponent) is not int or type(mantissa) is not int:
                raise CodecError(f"decimal fraction needs integer exponent and mantissa, got {[exponent, mantissa]!r}")
            if not -MAX_DECIMAL_SCALE <= exponent <= 0:
                raise CodecError(f"decimal exponent {exponent} outside -{MAX_DECIMAL_SCALE}..0")
            return Literal(render_decimal(exponent, mantissa), datatype=_DT_DECIMAL, normalize=False)
        if type(item) is list:
            return self._structured(item)
        raise CodecError(f"unexpected {type(item).__name__} where an RDF term belongs: {item!r}")

    def _structured(self, item: list[object]) -> Term:
        n = len(item)
        first = item[0] if n else None
        if n == 1 and type(first) is str:
            return BNode(first)
        if n == 2:
            second = item[1]
            if type(first) is int:
                return self.iri(first, second)
            if type(first) is str and type(second) is str:
                try:
                    return Literal(first, lang=second)
                except ValueError as exc:
                    raise CodecError(f"bad language tag {second!r}: {exc}") from exc
            if type(first) is str and type(second) is int:
                if not 0 <= second < len(WELL_KNOWN_DATATYPES):
                    raise CodecError(f"unknown well-known datatype code {second}")
                datatype = URIRef(WELL_KNOWN_DATATYPES[second])
                return Literal(first, datatype=datatype, normalize=False)
        if n == 3 and type(first) is str:
            return Literal(first, datatype=self.iri(item[1], item[2]), normalize=False)
        raise CodecError(f"malformed term {item!r}")


def load_cbor(data: bytes) -> object:
    """One CBOR item, with only the tags this package's formats allow
    turned into values (others stay :class:`cbor2.CBORTag`); raises
    :class:`CodecError` and nothing else."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise CodecError(f"expected bytes, got {type(data).__name__}")
    data = bytes(data)
    if not data:
        raise CodecError("empty payload")
    stream = io.BytesIO(data)
    try:
        item = cbor2.CBORDecoder(stream, semantic_decoders=_SEMANTIC_DECODERS, max_depth=_MAX_DEPTH).decode()
    except CodecError:
        raise
    except Exception as exc:  # cbor2 raises several types; all mean malformed input
        cause = exc.__cause__
        if isinstance(cause, CodecError):
            raise CodecError(str(cause)) from exc
        raise CodecError(f"malformed CBOR: {exc}") from exc
    if stream.tell() != len(data):
        raise CodecError(f"{len(data) - stream.tell()} trailing bytes after the CBOR item")
    return item


def _text_list(item: object, what: str) -> list[str]:
    if type(item) is not list or any(type(x) is not str for x in item):
        raise CodecError(f"{what} must be an array of text strings, got {item!r}")
    return item


def _prefix_table(item: object) -> list[str]:
    """Resolve the prefix table: text, or ``[base, suffix]`` extending an earlier entry."""
    if type(item) is not list:
        raise CodecError(f"prefix table must be an array, got {item!r}")
    table: list[str] = []
    total = 0
    for i, entry in enumerate(item):
        if type(entry) is str:
            table.append(entry)
        elif type(entry) is list and len(entry) == 2 and type(entry[0]) is int and type(entry[1]) is str:
            base = entry[0]
            if not 0 <= base < i:
                raise CodecError(f"prefix entry {i} extends entry {base}, which is not an earlier entry")
            table.append(table[base] + entry[1])
        else:
            raise CodecError(f"prefix entry {i} must be text or [base index, suffix], got {entry!r}")
        total += len(table[-1])
        if total > MAX_PREFIX_TABLE_CHARS:
            # Chained entries and stringrefs could otherwise expand a few
            # bytes into gigabytes of IRIs.
            raise CodecError(f"prefix table exceeds {MAX_PREFIX_TABLE_CHARS} characters")
    return table


def decode_cbor(data: bytes) -> QueryResult:
    """Decode compact CBOR; raises :class:`CodecError` on any malformed input."""
    item = load_cbor(data)
    if type(item) is bool:
        return AskResult(item)
    if type(item) is not list or len(item) not in (3, 4):
        raise CodecError("top level must be a bool (ASK) or [vars, prefixes, rows(, true)]")
    head, prefixes, body = item[0], item[1], item[2]
    truncated = len(item) == 4
    if truncated and item[3] is not True:
        raise CodecError(f"4th top-level element must be true (truncated), got {item[3]!r}")
    decoder = _TermDecoder(_prefix_table(prefixes))
    if type(body) is not list:
        raise CodecError(f"rows must be an array, got {body!r}")
    term = decoder.term
    if head is None:
        triples = []
        for i, triple in enumerate(body):
            if type(triple) is not list or len(triple) != 3:
                raise CodecError(f"triple {i} must be an array of 3 terms, got {triple!r}")
            if None in triple:
                raise CodecError(f"triple {i}: terms cannot be null")
            decoded = (term(triple[0]), term(triple[1]), term(triple[2]))
            _check_triple(decoded, f"triple {i}")
            triples.append(decoded)
        return GraphResult(tuple(triples), truncated)
    variables = _text_list(head, "variables")
    _check_vars(variables)
    width = len(variables)
    rows = []
    for i, row in enumerate(body):
        if type(row) is not list or len(row) != width:
            raise CodecError(f"row {i} must be an array of {width} values, got {row!r}")
        try:
            rows.append(tuple(None if value is None else term(value) for value in row))
        except CodecError as exc:
            raise CodecError(f"row {i}: {exc}") from None
    return SelectResult(tuple(variables), tuple(rows), truncated)


# --------------------------------------------------------------------------
# SPARQL 1.1 Query Results JSON
# --------------------------------------------------------------------------


def _json_term(term: object) -> dict[str, str]:
    if isinstance(term, Literal):
        out = {"type": "literal", "value": str(term)}
        if term.language is not None:
            out["xml:lang"] = term.language
        elif term.datatype is not None:
            out["datatype"] = str(term.datatype)
        return out
    if isinstance(term, URIRef):
        return {"type": "uri", "value": str(term)}
    if isinstance(term, BNode):
        return {"type": "bnode", "value": str(term)}
    raise CodecError(f"not an RDF term: {term!r}")


def _json_bindings(variables: Sequence[str], rows: Iterable[Sequence[object]]) -> list[dict[str, dict[str, str]]]:
    return [
        {name: _json_term(value) for name, value in zip(variables, row, strict=True) if value is not None}
        for row in rows
    ]


def encode_json(result: QueryResult) -> bytes:
    """SPARQL 1.1 Query Results JSON, UTF-8, no insignificant whitespace.

    Two members beyond the W3C format, which SPARQL-JSON consumers ignore:
    ``"truncated": true`` when the server stopped at its row limit, and
    ``"graph": true`` on a CONSTRUCT/DESCRIBE result, written as bindings of
    ``?subject ?predicate ?object`` (one per triple, in order).
    """
    doc: dict[str, object]
    if isinstance(result, AskResult):
        if not isinstance(result.value, bool):
            raise CodecError(f"ASK value must be a bool, got {result.value!r}")
        doc = {"head": {}, "boolean": result.value}
    elif isinstance(result, SelectResult):
        _check_vars(result.variables)
        doc = {
            "head": {"vars": list(result.variables)},
            "results": {"bindings": _json_bindings(result.variables, result.rows)},
        }
    elif isinstance(result, GraphResult):
        for i, triple in enumerate(result.triples):
            _check_triple(triple, f"triple {i}")
        doc = {
            "head": {"vars": list(GRAPH_VARS)},
            "results": {"bindings": _json_bindings(GRAPH_VARS, result.triples)},
            "graph": True,
        }
    else:
        raise CodecError(f"not a query result: {result!r}")
    if not isinstance(result, AskResult) and result.truncated:
        doc["truncated"] = True
    try:
        return json.dumps(doc, ensure_ascii=False, separators=(",", ":")).encode("utf-8")
    except UnicodeEncodeError as exc:
        raise CodecError(f"text is not encodable as UTF-8: {exc}") from exc


def _json_member(obj: dict[str, object], key: str, kind: type, what: str, default: object = _ABSENT) -> Any:
    value = obj.get(key, default)
    if value is _ABSENT:
        raise CodecError(f"{what} lacks {key!r}")
    if value is not default and type(value) is not kind:
        raise CodecError(f"{what}: {key!r} must be a {kind.__name__}, got {value!r}")
    return value


class _JsonTermDecoder:
    __slots__ = ("cache",)

    def __init__(self) -> None:
        self.cache: dict[tuple[object, ...], Term] = {}

    def term(self, obj: object) -> Term:
        if type(obj) is not dict:
            raise CodecError(f"an RDF term must be a JSON object, got {obj!r}")
        key = tuple(obj.items())
        try:
            cached = self.cache.get(key)
        except TypeError:
            raise CodecError(f"malformed RDF term {obj!r}") from None
        if cached is None:
            cached = self.cache[key] = self._build(obj)
        return cached

    @staticmethod
    def _build(obj: dict[str, object]) -> Term:
        kind = _json_member(obj, "type", str, "RDF term")
        value = _json_member(obj, "value", str, "RDF term")
        if kind == "uri":
            return URIRef(value)
        if kind == "bnode":
            return BNode(value)
        if kind not in ("literal", "typed-literal"):  # typed-literal: SPARQL 1.0 JSON
            raise CodecError(f"unsupported RDF term type {kind!r}")
        language = _json_member(obj, "xml:lang", str, "literal", None)
        datatype = _json_member(obj, "datatype", str, "literal", None)
        if language is not None:
            if datatype not in (None, _DT_LANGSTRING):
                raise CodecError(f"literal has both xml:lang {language!r} and datatype {datatype!r}")
            try:
                return Literal(value, lang=language)
            except ValueError as exc:
                raise CodecError(f"bad language tag {language!r}: {exc}") from exc
        if datatype is not None:
            return Literal(value, datatype=URIRef(datatype), normalize=False)
        if kind == "typed-literal":
            raise CodecError("typed-literal without datatype")
        return Literal(value)


def decode_json(data: bytes) -> QueryResult:
    """Decode SPARQL 1.1 Query Results JSON (plus the two extra members).

    Strict where a lossy reading would follow: the payload must be UTF-8, a
    binding may only name variables from ``head.vars``, and lone surrogates
    (which no UTF-8 consumer could carry on) are refused.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise CodecError(f"expected bytes, got {type(data).__name__}")
    try:
        text = bytes(data).decode("utf-8")
        doc = json.loads(text)
        if "\\u" in text and re.search(r"\\u[dD][89a-fA-F]", text):
            json.dumps(doc, ensure_ascii=False).encode("utf-8")  # raises on a lone surrogate
    except (ValueError, RecursionError) as exc:
        raise CodecError(f"malformed JSON: {exc}") from exc
    if type(doc) is not dict:
        raise CodecError("SPARQL results JSON must be an object")
    head = _json_member(doc, "head", dict, "results document")
    if "boolean" in doc:
        if "results" in doc:
            raise CodecError("results document has both 'boolean' and 'results'")
        return AskResult(_json_member(doc, "boolean", bool, "ASK result"))
    results = _json_member(doc, "results", dict, "results document")
    bindings = _json_member(results, "bindings", list, "'results'")
    variables = _json_member(head, "vars", list, "'head'")
    _text_list(variables, "head.vars")
    _check_vars(variables)
    graph = _json_member(doc, "graph", bool, "results document", False)
    truncated = _json_member(doc, "truncated", bool, "results document", False)
    known = set(variables)
    term = _JsonTermDecoder().term
    rows = []
    for i, binding in enumerate(bindings):
        if type(binding) is not dict:
            raise CodecError(f"binding {i} must be an object, got {binding!r}")
        for name in binding:
            if name not in known:
                raise CodecError(f"binding {i} names variable {name!r} that is not in head.vars")
        try:
            rows.append(tuple(term(binding[name]) if name in binding else None for name in variables))
        except CodecError as exc:
            raise CodecError(f"binding {i}: {exc}") from None
    if graph:
        if tuple(variables) != GRAPH_VARS:
            raise CodecError(f"a graph result must bind {list(GRAPH_VARS)}, got {variables!r}")
        triples = []
        for i, triple in enumerate(rows):
            if None in triple:
                raise CodecError(f"triple {i} leaves a position unbound")
            triples.append(_check_triple(triple, f"triple {i}"))
        return GraphResult(tuple(triples), truncated)
    return SelectResult(tuple(variables), tuple(rows), truncated)


# ------------------------------------------------------ embedded graphs

#: CBOR tag 24: an embedded CBOR data item (RFC 8949 section 3.4.5.1).
EMBEDDED_CBOR: Final = 24


def graph_item(triples: Iterable[Triple]) -> cbor2.CBORTag:
    """Triples as a compact graph embedded in a bigger message (a patch, a delta)."""
    return cbor2.CBORTag(EMBEDDED_CBOR, encode_cbor(GraphResult(tuple(triples))))


def decode_graph_item(item: object, what: str) -> tuple[Triple, ...]:
    """The triples of a :func:`graph_item` (raises :class:`CodecError`)."""
    if not isinstance(item, cbor2.CBORTag) or item.tag != EMBEDDED_CBOR or not isinstance(item.value, bytes):
        raise CodecError(f"{what}: expected tag 24 wrapping a compact graph")
    graph = decode_cbor(item.value)
    if not isinstance(graph, GraphResult):
        raise CodecError(f"{what}: expected a graph, not a {type(graph).__name__}")
    return graph.triples
