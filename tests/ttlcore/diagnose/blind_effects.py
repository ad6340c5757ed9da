"""Effects outside the diagnosis's named set, for blind tests only (``--effect-module``).

The diagnosis never loads this module: it must find these effects through its witnesses,
witness effects and frequency-dependent couplings.  The filters are applied here in the
time domain through the FFT of the whole simulated series (the simulator is run in one
chunk by the tests), with the analog responses written out independently of
``ttlcore.effects.filters.rational_basis``:

- ``blind-resonance``: ``g * w0^2 / (w0^2 - w^2 + i w w0 / Q)`` (a mechanical resonance,
  gain ``g Q`` at ``f0``);
- ``blind-lowpass``: ``g / (1 + i f / fc)`` (a first-order path);
- ``blind-witness``: a plain DWS channel on any link, after 0, 1 or 2 light travel times
  (the simulator's delays for one; for two, the series is shifted by twice the mean arm
  before the simulator's delay).
"""

import numpy as np

from ttlcore.effects import Column, Effect, EffectInjection, Part
from ttlcore.errors import ConfigError


def _filter(x, fs, h):
    n = x.size
    f = np.fft.rfftfreq(2 * n, 1 / fs)
    return np.fft.irfft(np.fft.rfft(x, 2 * n) * h(f), 2 * n)[:n]


class _OneChunk(EffectInjection):
    def link_signal(self, ctx):
        if ctx.n0 != 0:
            raise ConfigError(
                f"{self.name}: filtered through the FFT of one chunk; simulate with --chunk covering the run"
            )
        return super().link_signal(ctx)


class _Blind(Effect):
    parameters = {"source": "12.phi", "link": "12", "delay": 0, "f0": 0.1, "q": 10.0, "fc": 0.05}

    def injection(self, values, name=None):
        return _OneChunk(self, values, name)

    def response(self, f):
        return np.ones_like(f, dtype=complex)

    def columns(self, data):
        m, a = self.options["source"].split(".")
        w = data.witness(m, a)
        x = w if data.names_only else _filter(w, data.fs, self.response)
        n = int(self.options["delay"])
        if n == 2 and not data.names_only:  # one extra light travel time (mean) before the simulator's delay
            tau = float(np.mean(data.ltt[["12", "23", "31", "13", "32", "21"].index(self.options["link"])]))
            f = np.fft.rfftfreq(2 * x.size, 1 / data.fs)
            x = np.fft.irfft(np.fft.rfft(x, 2 * x.size) * np.exp(-2j * np.pi * f * tau), 2 * x.size)[: x.size]
        return [Column(f"{self.name}.gain", [Part(self.options["link"], x, n > 0)], "m/rad", 1e-3)]


class BlindResonance(_Blind):
    name = "blind-resonance"

    def response(self, f):
        w0, w = 2 * np.pi * float(self.options["f0"]), 2 * np.pi * f
        return w0**2 / (w0**2 - w**2 + 1j * w * w0 / float(self.options["q"]))


class BlindLowpass(_Blind):
    name = "blind-lowpass"

    def response(self, f):
        return 1.0 / (1.0 + 1j * f / float(self.options["fc"]))


class BlindWitness(_Blind):
    name = "blind-witness"


EFFECTS = [BlindResonance, BlindLowpass, BlindWitness]
