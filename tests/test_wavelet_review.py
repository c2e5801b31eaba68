"""Issue 39 reviewed from the command line (a user's pass over docs/wavelet.md): each test here
failed before its fix. Small scenes and cubes (R <= 8) so the module runs in seconds."""
from __future__ import annotations



from prt_torch.params import parse_value


def test_parse_value_reads_exponent_notation_as_a_number():
    """PyYAML (YAML 1.1) reads '1e-3' as the string '1e-3' (it wants '1.0e-3'), so every numeric CLI
    option and spec value typed that way was refused ('--hit-offset '1e-3'; accepted: a real number').
    The values are Python's own float literals."""
    assert parse_value("1e-3") == 1e-3 and isinstance(parse_value("1e-3"), float)
    assert parse_value("2E6") == 2e6
    assert parse_value("-5e+2") == -500.0
    assert parse_value(".5e1") == 5.0
    assert parse_value("1.0e-3") == 1e-3  # YAML's own form still a float
    assert parse_value("3") == 3 and isinstance(parse_value("3"), int)
    assert parse_value("e5") == "e5" and parse_value("1e") == "1e" and parse_value("1e-3x") == "1e-3x"  # not numbers
