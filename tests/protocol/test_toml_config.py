"""The one TOML config idiom (protocol/toml_config.py, protocol/config_fields.py): typed reading
of nested tables, lists of tables and tagged unions, one-line errors that name the file, the table,
the field and the value, checks that hold for configs built in code, and writing back."""

from __future__ import annotations

import enum
import subprocess
import sys
from dataclasses import dataclass, field
from typing import Literal

import pytest

from protocol.config_fields import FieldError, check, internal, option, validate
from protocol.errors import ConfigError, UserError
from protocol.toml_config import dumps, load_toml, parse_toml, read_file, read_table


class Mode(enum.Enum):
    FAST = "fast"
    SLOW = "slow"


@dataclass(frozen=True, kw_only=True)
class Step:
    kind: Literal["hang", "vanish"]
    at_s: float = option(ge=0)

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class Apple:
    source: Literal["apple"] = "apple"
    fps: float = option(30.0, gt=0, le=120)
    mode: Mode = Mode.FAST
    steps: tuple[Step, ...] = ()

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class Pear:
    source: Literal["pear"] = "pear"
    serial: int | None = option(None, gt=0, must="must be the serial number")
    low: int = 0
    high: int = 10

    def __post_init__(self) -> None:
        validate(self)
        check(self.low < self.high, "low", self.low, f"must be below high ({self.high})")


@dataclass(frozen=True, kw_only=True)
class Clock:
    require_lock: bool = True
    names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class Node:
    node_id: str
    clock: Clock = field(default_factory=Clock)
    fruit: tuple[Apple | Pear, ...] = ()
    path: str = internal("")

    def __post_init__(self) -> None:
        validate(self)


TABLE = {
    "node_id": "n1",
    "clock": {"require_lock": False, "names": ["a", "b"]},
    "fruit": [
        {"source": "apple", "fps": 15, "mode": "slow", "steps": [{"kind": "hang", "at_s": 1}]},
        {"source": "pear", "serial": 7},
    ],
}


def test_reads_nested_tables_lists_and_tagged_unions_and_writes_them_back():
    node = read_table(Node, TABLE, "node.toml")
    assert node.clock == Clock(require_lock=False, names=("a", "b"))
    apple, pear = node.fruit
    assert isinstance(apple, Apple) and apple.fps == 15.0 and isinstance(apple.fps, float)
    assert apple.mode is Mode.SLOW and apple.steps == (Step(kind="hang", at_s=1.0),)
    assert pear == Pear(serial=7)
    text = dumps(node, comment="written by a test")
    assert text.startswith("# written by a test\n") and "[[fruit]]" in text and "path" not in text
    assert "serial = 7" in text and "None" not in text
    assert read_table(Node, parse_toml(text, "again.toml"), "again.toml") == node


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"clock": {"require_lok": True}}, "node.toml: unknown option 'clock.require_lok'"),
        ({"clock": {"require_lock": "yes"}}, "node.toml: clock.require_lock = 'yes': must be true"),
        ({"clock": {"names": ["a", 3]}}, "node.toml: clock.names[1] = 3: must be a string"),
        ({"clock": 5}, "node.toml: clock: expected a table"),
        ({"fruit": [{"source": "plum"}]}, "fruit[0].source = 'plum': choose one of 'apple', 'pe"),
        ({"fruit": [{}]}, "node.toml: 'fruit[0].source' is required: choose one of 'apple'"),
        ({"fruit": [{"source": "apple", "fsp": 1}]}, "unknown option 'fruit[0].fsp'"),
        ({"fruit": [{"source": "apple", "fps": 0}]}, "node.toml: fruit[0].fps = 0: must be > 0"),
        ({"fruit": [{"source": "apple", "mode": "warp"}]}, "fruit[0].mode = 'warp': 'warp' is"),
        ({"fruit": [{"source": "pear", "serial": -1}]}, "fruit[0].serial = -1: must be the ser"),
        ({"fruit": [{"source": "pear", "low": 20}]}, "node.toml: fruit[0].low = 20: must be bel"),
        ({"fruit": [{"source": "apple", "steps": [{"kind": "hang"}]}]}, "'fruit[0].steps[0].at_s"),
        ({"fruit": {"source": "apple"}}, "node.toml: fruit = {'source': 'apple'}: must be a list"),
        ({"node_id": 3}, "node.toml: node_id = 3: must be a string"),
        ({"path": "x"}, "unknown option 'path'"),
    ],
)
def test_a_bad_table_fails_in_one_line_naming_file_table_field_and_value(change, message):
    with pytest.raises(ConfigError) as info:
        read_table(Node, {**TABLE, **change}, "node.toml")
    text = str(info.value)
    assert message in text and "\n" not in text
    assert isinstance(info.value, UserError) and isinstance(info.value, ValueError)


def test_an_unknown_key_is_refused_with_the_keys_that_exist():
    with pytest.raises(ConfigError, match=r"\[clock\] has: require_lock, names$"):
        read_table(Node, {"node_id": "n", "clock": {"treshold": 1}}, "node.toml")
    with pytest.raises(ConfigError, match="'node_id' is required"):
        read_table(Node, {}, "node.toml")


def test_a_config_built_in_code_is_checked_the_same_way():
    with pytest.raises(FieldError, match=r"^fps = -1: must be > 0 and <= 120$"):
        Apple(fps=-1)
    with pytest.raises(FieldError, match="require_lock = 'no'"):
        Clock(require_lock="no")  # type: ignore[arg-type]
    with pytest.raises(FieldError, match="kind = 'explode'"):
        Step(kind="explode", at_s=0)  # type: ignore[arg-type]
    assert Clock(names=["x"]).names == ("x",)  # type: ignore[arg-type]
    assert Apple(mode="fast").mode is Mode.FAST  # type: ignore[arg-type]


def test_base_keeps_the_values_a_partial_table_leaves_out():
    base = Node(node_id="n", clock=Clock(require_lock=False, names=("a",)))
    again = read_table(Node, {"clock": {"names": ["b"]}}, "override.toml", base=base)
    assert again == Node(node_id="n", clock=Clock(require_lock=False, names=("b",)))


def test_files_that_are_missing_or_not_toml_say_so(tmp_path):
    with pytest.raises(ConfigError, match=r"node config .*missing\.toml does not exist"):
        load_toml(tmp_path / "missing.toml", "node config")
    bad = tmp_path / "bad.toml"
    bad.write_text("[clock\n")
    with pytest.raises(ConfigError, match=r"bad\.toml is not valid TOML"):
        read_file(Node, bad, "node config")
    good = tmp_path / "good.toml"
    good.write_text(dumps(Node(node_id="n")))
    assert read_file(Node, good, "node config") == Node(node_id="n")


def test_the_module_imports_nothing_heavy():
    code = (
        "import sys, protocol.toml_config\n"
        "print(','.join(m for m in ('numpy', 'cv2', 'h5py', 'zmq', 'tomli_w') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_arrays_of_scalars_are_written_on_one_line_and_read_back():
    """As people write them, and as a case's config.toml (whose text is hashed to decide whether
    a case folder may resume) has always been written: one line per array of numbers."""
    from protocol.toml_config import dumps_table, parse_toml

    table = {"room_bounds_m": [-3.0, -3.0, 0.0, 3.0, 3.0, 3.0], "names": ["a, b", "c]"]}
    text = dumps_table(table)
    assert "room_bounds_m = [-3.0, -3.0, 0.0, 3.0, 3.0, 3.0]\n" in text
    assert parse_toml(text, "written") == table
