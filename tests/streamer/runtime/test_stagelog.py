"""Unit tests of :mod:`streamer.runtime.stagelog`: a stage's log records, plain or JSON lines."""

import io
import json
import logging

from streamer.runtime.stagelog import JsonFormatter, StageLogger, configure_logging


def test_json_lines_carry_run_stage_and_index():
    stream = io.StringIO()
    root = logging.getLogger()
    saved = root.handlers[:], root.level
    try:
        configure_logging("DEBUG", json_lines=True, stream=stream)
        log = StageLogger(logging.getLogger("streamer.runtime.stage.fitter"), {"run": "r1", "stage": "fitter"})
        log.info("segment %d done", 3, extra={"index": 3})
        try:
            raise ValueError("bad segment")
        except ValueError:
            log.exception("failed")
    finally:
        root.handlers[:], _ = saved
        root.setLevel(saved[1])
    first, second = (json.loads(line) for line in stream.getvalue().splitlines())
    assert first["message"] == "segment 3 done"
    assert (first["run"], first["stage"], first["index"]) == ("r1", "fitter", 3)
    assert first["level"] == "INFO" and first["logger"] == "streamer.runtime.stage.fitter"
    assert "index" not in second and second["level"] == "ERROR"
    assert "ValueError: bad segment" in second["exception"]


def test_plain_text_and_the_level():
    stream = io.StringIO()
    root = logging.getLogger()
    saved = root.handlers[:], root.level
    try:
        configure_logging("WARNING", stream=stream)
        logging.getLogger("x").info("hidden")
        logging.getLogger("x").warning("shown")
    finally:
        root.handlers[:], _ = saved
        root.setLevel(saved[1])
    assert "hidden" not in stream.getvalue()
    assert stream.getvalue().rstrip().endswith("WARNING x: shown")


def test_json_formatter_without_extras():
    record = logging.LogRecord("n", logging.INFO, __file__, 1, "m %s", ("a",), None)
    out = json.loads(JsonFormatter().format(record))
    assert out["message"] == "m a" and not {"run", "stage", "index"} & set(out)
