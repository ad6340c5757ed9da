"""The checks the type pass of streamer and stages added (issue 34): a value used where
it is not there yet is a clear error naming it, and a recorded field of the wrong shape is
read as unusable, not a crash."""

from __future__ import annotations

from pathlib import Path

import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import x25519

from streamer.bus import security
from streamer.recording.recorder import RecordedMessage, RecordedSegment, Recording, RecordingError
from streamer.runtime.stage import StageConfig
from streamer.tools.inspect_model import recorded_fits


def test_a_ca_key_that_cannot_sign_is_refused_by_name(tmp_path):
    d = security.ensure_credentials(tmp_path / "creds", roles=("fitter",))
    key = x25519.X25519PrivateKey.generate()  # a key exchange key: no certificate issuer
    (d / "ca.key").write_bytes(
        key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    )
    (d / "fitter.pem").unlink()  # a certificate to issue again
    with pytest.raises(security.CredentialsError, match=r"ca\.key: a .*X25519PrivateKey.*cannot sign certificates"):
        security.ensure_credentials(d, roles=("fitter",))
    assert not (d / "fitter.pem").exists()  # nothing half-written


def test_recorded_fits_leave_out_a_summary_without_names():
    """A summary in FitResult.to_json layout (coefficients by name) that names none has no
    coefficients: left out like any unusable fit, the others read."""
    named = {"index": 1, "names": ["a", "b"], "coefficients": {"a": 1.0, "b": 2.0}, "sigma": {"a": 0.1, "b": 0.2}}
    unnamed = {"index": 0, "coefficients": {"a": 1.0}, "sigma": {"a": 0.1}}
    rec = Recording(
        Path("fitter.mcap"),
        messages=[RecordedMessage("fit/summary", i, "json", data=d) for i, d in enumerate((unnamed, named))],
    )
    fits = recorded_fits([rec])
    assert [f["index"] for f in fits] == [1]
    assert fits[0]["coefficients"] == [1.0, 2.0] and fits[0]["names"] == ["a", "b"]


def test_a_recorded_segment_is_a_decoded_one():
    with pytest.raises(RecordingError, match="fit: a incomplete message, not a decoded segment"):
        RecordedSegment.of(RecordedMessage("fit", 0, "incomplete"))


def test_stage_parts_used_before_they_exist_are_named(tmp_path):
    from stages.fitter.fitter import Fitter
    from stages.monitor.monitor import Monitor

    fitter = Fitter(StageConfig(run="u", recordings=tmp_path))
    with pytest.raises(RuntimeError, match="the recorder is used outside run"):
        fitter.live_recorder.flush()
    with pytest.raises(RuntimeError, match="the bus is used outside run"):
        fitter.live_bus.close()
    with pytest.raises(RuntimeError, match="rolling fit is used before a segment started it"):
        assert fitter.started_rolling.settings  # (raises first)
    monitor = Monitor(StageConfig(run="u", recordings=tmp_path))
    with pytest.raises(RuntimeError, match="monitor: the Rerun recording is used before"):
        monitor.text("log", "too early")
