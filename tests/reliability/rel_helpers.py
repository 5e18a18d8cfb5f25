"""Assertions shared by the bad-input suite."""

TINY_EVAL = ["--num-agents", "4", "--area", "2", "--episodes", "1", "--max-steps", "3", "--no-progress"]


def assert_usage_error(res, *phrases: str) -> None:
    """A usage error: exit code 2, one ``Error:`` line holding every phrase (case-insensitive), no traceback."""
    text = res.output
    assert res.exit_code == 2, text
    assert isinstance(res.exception, SystemExit), repr(res.exception)
    errors = [line for line in text.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1, text
    for p in phrases:
        assert p.lower() in errors[0].lower(), (p, errors[0])
    assert "Traceback" not in text
