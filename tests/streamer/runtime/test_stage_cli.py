"""Unit tests of :mod:`streamer.runtime.stage_cli`: a stage's command line into its
:class:`~streamer.runtime.stage_config.StageConfig` (parsing only: no process, no bus)."""

import argparse
import json
from pathlib import Path

import pytest

from streamer.runtime.settings import SettingsError
from streamer.runtime.stage_cli import _set_common_options, add_common_options, config_from_args, stage_arguments


def parse(*argv: str) -> argparse.Namespace:
    p = stage_arguments(argparse.ArgumentParser())
    add_common_options(p)
    return p.parse_args(list(argv))


def test_the_command_line_alone():
    config = config_from_args(parse("--run", "r1", "--name", "fitter-b", "--recordings", "rec"))
    assert (config.run, config.stage, config.recordings) == ("r1", "fitter-b", Path("rec"))
    assert config.zenoh.mode is None and config.zenoh.connect is None


def test_connect_without_listen_is_a_client_of_the_router():
    config = config_from_args(parse("--run", "r1", "--connect", "tcp/10.0.0.5:7447", "--connect", "tcp/10.0.0.6:7447"))
    assert config.zenoh.mode == "client"
    assert config.zenoh.connect == ("tcp/10.0.0.5:7447", "tcp/10.0.0.6:7447")
    both = config_from_args(parse("--run", "r1", "--connect", "tcp/a:1", "--listen", "tcp/127.0.0.1:0"))
    assert both.zenoh.mode is None and both.zenoh.listen == ("tcp/127.0.0.1:0",)
    peer = config_from_args(parse("--run", "r1", "--connect", "tcp/a:1", "--mode", "peer"))
    assert peer.zenoh.mode == "peer"


def test_the_command_line_overrides_the_config_file(tmp_path):
    path = tmp_path / "fitter.config.json"
    path.write_text(
        json.dumps({"run": "r0", "stage": "fitter", "zenoh": {"listen": ["tcp/127.0.0.1:0"]}, "poll_interval": 0.7})
    )
    args = parse("--config", str(path), "--run", "r1", "--cache", "9", "--no-record-inputs")
    config = config_from_args(args)
    assert (config.run, config.stage, config.zenoh.listen) == ("r1", "fitter", ("tcp/127.0.0.1:0",))
    _set_common_options(config, args, default_poll_interval=0.05)
    assert (config.cache, config.record_inputs, config.poll_interval) == (9, False, 0.7)  # the file's interval
    bare = config_from_args(parse("--run", "r1"))
    _set_common_options(bare, parse("--run", "r1"), default_poll_interval=0.05)
    assert bare.poll_interval == 0.05 and bare.record_inputs is True
    _set_common_options(bare, parse("--run", "r1", "--poll-interval", "0.3", "--history", "4"), 0.05)
    assert (bare.poll_interval, bare.history) == (0.3, 4)


def test_a_bad_value_names_its_field(tmp_path):
    with pytest.raises(SettingsError, match="run"):
        config_from_args(parse("--run", "no spaces/allowed"))
    path = tmp_path / "c.json"
    path.write_text(json.dumps({"run": "r1", "cache": 0}))
    with pytest.raises(SettingsError, match="cache"):
        config_from_args(parse("--config", str(path)))
