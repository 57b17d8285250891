"""Every error class coapkb defines sits under the one root, CoapkbError."""

from __future__ import annotations

import importlib
import inspect
import pkgutil

import pytest

import coapkb
from coapkb.errors import CoapkbError

#: Not errors of the package's API: the CoAP reliability layer's timeout is a
#: TimeoutError that the CoAP client turns into PeerUnreachable before it
#: leaves the transport.
INTERNAL = frozenset({"coapkb.transport.coap.reliability.layer.ExchangeTimeout"})


def _error_classes() -> list[type[BaseException]]:
    found = []
    for info in pkgutil.walk_packages(coapkb.__path__, "coapkb."):
        if info.name == "coapkb.__main__":
            continue
        module = importlib.import_module(info.name)
        for name, obj in vars(module).items():
            if (
                inspect.isclass(obj)
                and issubclass(obj, BaseException)
                and obj.__module__ == info.name
                and not name.startswith("_")  # private control flow that never leaves its module
                and f"{info.name}.{name}" not in INTERNAL
            ):
                found.append(obj)
    return found


def test_the_package_defines_errors_and_all_derive_from_the_root() -> None:
    classes = _error_classes()
    names = {c.__name__ for c in classes}
    assert {"ConfigError", "KBError", "QueryFailed", "QueryError", "TransportError", "CodecError",
            "WireError", "TeamError", "LinkEmulationError", "UserError"} <= names
    assert [c.__qualname__ for c in classes if not issubclass(c, CoapkbError)] == []


@pytest.mark.parametrize("module, name, also", [
    ("coapkb.config", "ConfigError", ValueError),
    ("coapkb.wire.codec", "CodecError", ValueError),
    ("coapkb.transport.envelope", "WireError", ValueError),
    ("coapkb.bench.linkemu", "LinkEmulationError", RuntimeError),
])
def test_errors_keep_their_builtin_base_for_existing_callers(module: str, name: str, also: type) -> None:
    assert issubclass(getattr(importlib.import_module(module), name), also)


def test_the_error_table_names_every_class_directly_under_the_root() -> None:
    import coapkb.errors

    table = coapkb.errors.__doc__ or ""
    direct = {c.__name__ for c in _error_classes() if CoapkbError in c.__bases__}
    assert {name for name in direct if f"``{name}``" not in table} == set()
