"""The one configuration loader (core.config): unknown keys, nested sections, coercion, wrong kinds."""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from core.config import config_from_dict
from core.errors import FormatError
from triangulate.reconstruct import TriangulateConfig


@dataclass(frozen=True)
class Inner:
    gate_m: float = 0.2
    cams: tuple[str, ...] = ()


@dataclass(frozen=True)
class Outer:
    n: int = 3
    name: str = "x"
    limit: float | None = None
    inner: Inner = field(default_factory=Inner)


def test_nested_sections_and_coercion():
    cfg = config_from_dict(Outer, {"n": "5", "limit": 2, "inner": {"gate_m": 1, "cams": ["a", "b"]}})
    assert cfg == Outer(n=5, limit=2.0, inner=Inner(gate_m=1.0, cams=("a", "b")))
    assert isinstance(cfg.limit, float) and isinstance(cfg.inner.gate_m, float)
    assert config_from_dict(Outer, {"limit": None}).limit is None


def test_unknown_keys_anywhere_list_the_valid_ones():
    with pytest.raises(
        FormatError, match=r"field 'inner': unknown keys \['gate'\]; valid keys: \['cams', 'gate_m'\]"
    ):
        config_from_dict(Outer, {"inner": {"gate": 1}}, path="p.toml")
    with pytest.raises(FormatError, match=r"unknown keys \['nn'\]"):
        config_from_dict(Outer, {"nn": 1})
    # a stage config: the nested match section is checked by the same loader
    with pytest.raises(ValueError, match=r"match.*unknown keys \['thetta_px'\]"):
        TriangulateConfig.from_dict({"match": {"thetta_px": 3}})
    assert TriangulateConfig.from_dict({"match": {"theta_px": 30}}).match.theta_px == 30


def test_wrong_kinds_name_the_key():
    with pytest.raises(FormatError, match=r"field 'inner.gate_m': expected float, got 'wide'"):
        config_from_dict(Outer, {"inner": {"gate_m": "wide"}})
    with pytest.raises(FormatError, match=r"field 'n': expected int, got 2.5"):
        config_from_dict(Outer, {"n": 2.5})
