"""Test-only fault injection into stage processes started by ``ttl run`` (on ``PYTHONPATH``).

``TTL_TEST_FAIL_HANDLE=<stage>``: that stage's ``handle`` raises on every input segment that
reaches it intact, as a stage with a defect would (tests/test_operations.py:
``test_a_stage_failing_every_segment_ends_the_run``).  Without the variable, nothing changes.
"""

import os

_FAIL = os.environ.get("TTL_TEST_FAIL_HANDLE")

if _FAIL:
    from streamer.runtime import stage as _stage

    _use = _stage.Stage._use

    def _failing_use(self, key, header, arrays, payload):
        if self.stage_name == _FAIL:

            def handle(header, arrays):
                raise RuntimeError(f"injected failure of {_FAIL}.handle (TTL_TEST_FAIL_HANDLE)")

            self.handle = handle
        return _use(self, key, header, arrays, payload)

    _stage.Stage._use = _failing_use
