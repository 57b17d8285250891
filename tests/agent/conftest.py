"""Fixtures of the agent unit tests (defined in agent_helpers)."""

from agent_helpers import all_kbs, kbs, network, serve_kbs  # noqa: F401 -- registers the fixtures
