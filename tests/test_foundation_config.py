"""The one configuration loader (core.config): unknown keys, nested sections, coercion, wrong kinds."""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from roomcap.core.config import bounded, config_from_dict
from roomcap.core.errors import FormatError
from roomcap.triangulate.reconstruct import TriangulateConfig


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


@dataclass(frozen=True)
class Ranged:
    segment_s: float = bounded(0.5, 0.1, 10)
    frames: int = bounded(4, 2, 100)
    flag: bool = False


class SectionError(FormatError):
    pass


def test_booleans_as_words_and_ranges_checked_with_the_callers_error():
    assert config_from_dict(Ranged, {"flag": "yes"}).flag is True
    assert config_from_dict(Ranged, {"flag": 0}).flag is False
    assert config_from_dict(Ranged, {"flag": "1", "segment_s": 2}).segment_s == 2.0
    with pytest.raises(FormatError, match=r"field 'flag': expected bool, got 2"):
        config_from_dict(Ranged, {"flag": 2})
    with pytest.raises(SectionError, match=r"field 'rec.frames': 1 is outside the valid range \[2, 100\]"):
        config_from_dict(Ranged, {"frames": 1}, "rec", error=SectionError)
    with pytest.raises(SectionError, match=r"unknown keys \['fps'\]"):
        config_from_dict(Ranged, {"fps": 1}, "rec", error=SectionError)
    with pytest.raises(
        SectionError, match=r"expected a number in \[0.1, 10\], got 'x'|expected float, got 'x'"
    ):
        config_from_dict(Ranged, {"segment_s": "x"}, error=SectionError)
