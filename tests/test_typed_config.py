"""The strict mapping -> dataclass parser shared by recipes and run configs: every hint
kind against hand-written expectations, and the messages that name the field."""

from dataclasses import dataclass, field
from typing import Any, Literal

import pytest

from imac_data.config import parse_dataclass
from imac_data.errors import InputError


@dataclass
class Inner:
    size: int
    scale: float = 1.0


@dataclass
class Outer:
    name: str
    inner: Inner
    mode: Literal["a", "b"] = "a"
    sizes: tuple[int, ...] = ()
    table: dict[str, float] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)
    maybe: int | None = None
    flag: bool = False
    file: str = ""

    def __post_init__(self):
        if self.inner.size < 0:
            raise InputError("size must be >= 0")


def test_every_hint_kind_is_coerced():
    got = parse_dataclass(Outer, {"name": "x", "inner": {"size": 3, "scale": 2}, "mode": "b", "sizes": [1, 2],
                                  "table": {"k": 1}, "extra": {"any": [1, "two"]}, "maybe": None, "flag": True})
    assert got == Outer("x", Inner(3, 2.0), "b", (1, 2), {"k": 1.0}, {"any": [1, "two"]}, None, True)
    assert isinstance(got.inner.scale, float) and isinstance(got.table["k"], float)


@pytest.mark.parametrize("value, message", [
    ({"name": "x"}, "cfg: missing required field 'inner'"),
    ({"name": "x", "inner": {"size": 1}, "colour": 1}, r"cfg: unknown field\(s\) \['colour'\]"),
    ({"name": "x", "inner": {"size": "1"}}, "inner.size: expected an integer, got '1'"),
    ({"name": "x", "inner": {"size": True}}, "inner.size: expected an integer, got True"),
    ({"name": "x", "inner": {"size": 1}, "mode": "c"}, r"mode: must be one of \['a', 'b'\]"),
    ({"name": "x", "inner": {"size": 1}, "sizes": 3}, "sizes: expected a list, got int"),
    ({"name": "x", "inner": {"size": 1}, "sizes": [1, "2"]}, r"sizes\[1\]: expected an integer"),
    ({"name": "x", "inner": {"size": 1}, "table": {"k": "v"}}, "table.k: expected a number"),
    ({"name": "x", "inner": {"size": 1}, "maybe": 1.5}, "maybe: expected an integer"),
    ({"name": "x", "inner": {"size": -1}}, "^size must be >= 0$"),
    ({"name": "x", "inner": {"size": 1}, "file": "f"}, r"unknown field\(s\) \['file'\]"),
    ([1], "cfg: expected a mapping, got list"),
])
def test_errors_name_the_field(value, message):
    with pytest.raises(InputError, match=message):
        parse_dataclass(Outer, value, root="cfg", skip={"file"})


def test_a_nested_dataclass_check_is_placed_at_its_field():
    @dataclass
    class Checked:
        n: int

        def __post_init__(self):
            if self.n > 1:
                raise InputError("n must be at most 1")

    @dataclass
    class Holder:
        checked: Checked

    with pytest.raises(InputError, match="^checked: n must be at most 1$"):
        parse_dataclass(Holder, {"checked": {"n": 2}})
