"""vgq.cli_config: one dataclass -> flags / environment / JSON file bridge for every CLI."""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, field

import pytest

from vgq.cli_config import ConfigError, add_options, build, parse_text


@dataclass(frozen=True)
class Inner:
    d_range: tuple[float, float] = (0.5, 0.7)
    count: int = 3

    def __post_init__(self) -> None:
        if self.count < 1:
            raise ValueError(f"count must be >= 1, got {self.count}")


@dataclass(frozen=True)
class Outer:
    port: int = 8000
    rate: float = 1.5
    name: str = "a"
    loud: bool = False
    mode: str = field(default="fast", metadata={"choices": ("fast", "slow"), "help": "how to run"})
    limit: int | None = None
    inner: Inner = field(default_factory=Inner)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="t", exit_on_error=False)
    p.add_argument("--out")  # a flag of the CLI itself, not of the dataclass
    add_options(p, Outer)
    return p


def test_no_input_gives_the_defaults():
    assert build(Outer, parser().parse_args([])) == Outer()


def test_precedence_defaults_file_env_overrides_flags(tmp_path):
    f = tmp_path / "c.json"
    f.write_text(json.dumps({"port": 1, "rate": 2.0, "name": "file", "inner": {"count": 4}}))
    env = {"T_PORT": "2", "T_RATE": "3.5", "T_INNER_COUNT": "5", "OTHER": "x"}
    args = parser().parse_args(["--port", "3", "--out", "o"])
    c = build(Outer, args, environ=env, env_prefix="T_", file=f, overrides={"rate": 4.0})
    assert c.port == 3  # flag over environment over file
    assert c.rate == 4.0  # override over environment
    assert c.inner.count == 5  # environment over file
    assert c.name == "file"  # file over default
    assert c.inner.d_range == (0.5, 0.7)  # default kept


def test_types_from_text():
    args = parser().parse_args(
        ["--rate", "inf", "--loud", "--limit", "7", "--inner.d-range", "[0.4, 0.9]", "--name", "123"]
    )
    c = build(Outer, args)
    assert c.rate == float("inf") and c.loud is True and c.limit == 7 and c.name == "123"
    assert c.inner.d_range == (0.4, 0.9) and isinstance(c.inner.d_range, tuple)
    assert build(Outer, parser().parse_args(["--limit", "null"])).limit is None
    assert build(Outer, parser().parse_args(["--no-loud"]), environ={"T_LOUD": "1"}, env_prefix="T_").loud is False
    assert build(Outer, environ={"T_LOUD": "on"}, env_prefix="T_").loud is True


def test_choices_and_help_come_from_field_metadata():
    p = parser()
    assert build(Outer, p.parse_args(["--mode", "slow"])).mode == "slow"
    with pytest.raises(argparse.ArgumentError):
        p.parse_args(["--mode", "medium"])
    assert "how to run" in p.format_help()


@pytest.mark.parametrize(
    "argv, env, needle",
    [
        (["--port", "eighty"], {}, "--port"),
        ([], {"T_PORT": "eighty"}, "T_PORT"),
        ([], {"T_LOUD": "maybe"}, "T_LOUD"),
        (["--inner.d-range", "[1, 2, 3]"], {}, "--inner.d-range"),
        (["--inner.count", "0"], {}, "inner: count must be >= 1"),  # the dataclass's own check
    ],
)
def test_bad_values_name_the_field(argv, env, needle):
    with pytest.raises(ConfigError, match=needle.replace(".", r"\.")):
        build(Outer, parser().parse_args(argv), environ=env, env_prefix="T_")


def test_unknown_keys_are_refused(tmp_path):
    f = tmp_path / "c.json"
    f.write_text(json.dumps({"inner": {"bogus": 1}}))
    with pytest.raises(ConfigError, match="inner.bogus"):
        build(Outer, file=f)
    with pytest.raises(ConfigError, match="nope"):
        build(Outer, overrides={"nope": 1})
    with pytest.raises(ConfigError, match="inner"):
        build(Outer, overrides={"inner": 3})


def test_bad_files_are_named(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        build(Outer, file=tmp_path / "missing.json")
    f = tmp_path / "c.json"
    f.write_text("[1, 2]")
    with pytest.raises(ConfigError, match="c.json must hold a JSON object"):
        build(Outer, file=f)


def test_parse_text_keeps_strings_and_parses_json_for_containers():
    assert parse_text(str, "[1]", "x") == "[1]"
    assert parse_text(tuple[int, ...], "[1, 2]", "x") == (1, 2)
    assert parse_text(dict[str, int], '{"mug": 3}', "x") == {"mug": 3}
    with pytest.raises(ConfigError, match="x must be an integer"):
        parse_text(int, "1.5", "x")


def test_service_flags_win_over_vgq_environment(monkeypatch, capsys):
    from service.config import parse_args

    monkeypatch.setenv("VGQ_PORT", "9001")
    monkeypatch.setenv("VGQ_ACCESS_LOG", "yes")
    monkeypatch.setenv("VGQ_REQUEST_TIMEOUT_S", "2.5")
    s = parse_args(["--port", "9002", "--max-grasps", "10"])
    assert (s.port, s.access_log, s.request_timeout_s, s.max_grasps) == (9002, True, 2.5, 10)
    assert parse_args(["--no-access-log"]).access_log is False
    monkeypatch.setenv("VGQ_MAX_GRASPS", "many")
    with pytest.raises(SystemExit) as e:
        parse_args([])
    assert e.value.code == 2 and "VGQ_MAX_GRASPS must be an integer" in capsys.readouterr().err


def test_training_flags_reach_the_config():
    from training.__main__ import _config_from, build_parser
    from training.baseline import BaselineConfig
    from training.config import TrainConfig

    a = build_parser().parse_args(["train", "--data", "d", "--out", "o", "--base-lr", "0.01", "--optimizer", "adamw"])
    assert _config_from(a, TrainConfig) == TrainConfig(base_lr=0.01, optimizer="adamw")
    a = build_parser().parse_args(["baseline", "--data", "d", "--no-class-balance", "--columns", "vgqcnn"])
    assert _config_from(a, BaselineConfig) == BaselineConfig(class_balance=False, columns="vgqcnn")


def test_a_base_instance_takes_the_place_of_the_defaults(tmp_path):
    base = Outer(port=1, inner=Inner(d_range=(0.1, 0.2), count=9))
    f = tmp_path / "c.json"
    f.write_text(json.dumps({"inner": {"count": 4}}))
    c = build(Outer, base=base, file=f, overrides={"name": "b"})
    assert c == Outer(port=1, name="b", inner=Inner(d_range=(0.1, 0.2), count=4))  # sections merge
