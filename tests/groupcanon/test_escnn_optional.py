"""The escnn adapter is optional: its module imports without escnn and says how to install it when used.

Runs in the core environment (numpy 2, no escnn); the adapter itself is tested in test_escnn_adapter.py
(``make test-escnn``).
"""

from __future__ import annotations

import importlib.util

import pytest


def test_module_imports_without_escnn():
    import groupcanon.compat.escnn as adapter

    assert callable(adapter.from_escnn)


@pytest.mark.skipif(importlib.util.find_spec("escnn") is not None, reason="escnn is installed here")
def test_missing_escnn_raises_actionable_import_error():
    from groupcanon.compat.escnn import from_escnn

    with pytest.raises(ImportError, match=r"pip install 'egcbf\[escnn\]'") as info:
        from_escnn(object())
    assert "--no-deps escnn" in str(info.value)
    assert "make setup-escnn" in str(info.value)
