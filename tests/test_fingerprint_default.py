"""The fingerprint of the `default` preset (the README's main command) in the fast set: the very
check of `tests/test_fingerprint.py` (same stand-in MPC solve, same recorded data), whose own
`default` case runs with the slow set."""

from __future__ import annotations

from tests import test_fingerprint


def test_default_preset_computes_what_it_computed(monkeypatch):
    test_fingerprint.test_training_computes_what_it_computed("default", monkeypatch)
