"""A query's result taken as the kind its caller asked for (the result
types are the model's, :mod:`coapkb.model.results`)."""

from __future__ import annotations

from ..model.results import AskResult, QueryResult, SelectResult
from .errors import UnexpectedResult


def expect_select(result: QueryResult, what: str) -> SelectResult:
    """``result`` as a SELECT's rows; :class:`~.errors.UnexpectedResult`
    naming ``what`` (the query) if it is an ASK's answer or a graph."""
    if not isinstance(result, SelectResult):
        raise UnexpectedResult(f"{what}: expected SELECT rows, got {type(result).__name__}")
    return result


def expect_ask(result: QueryResult, what: str) -> AskResult:
    """``result`` as an ASK's answer; :class:`~.errors.UnexpectedResult`
    naming ``what`` (the query) if it is SELECT rows or a graph."""
    if not isinstance(result, AskResult):
        raise UnexpectedResult(f"{what}: expected an ASK answer, got {type(result).__name__}")
    return result
