"""The EMPS benchmark prepared as the benchmark's authors do: zero-phase low-pass of the encoder
position, central differences for velocity and acceleration, then decimation to 100 Hz."""
from __future__ import annotations

from pathlib import Path

import numpy as np

EMPS = Path(__file__).resolve().parent / "data" / "emps" / "DATA_EMPS.mat"
PUBLISHED = {"M": 95.11, "Fv": 203.5, "Fc": 20.39, "offset": -3.16}


def emps_request(decimate: int = 10) -> dict:
    import scipy.io
    from scipy.signal import butter, filtfilt
    d = scipy.io.loadmat(EMPS)
    t, q, vir, gtau = d["t"].ravel(), d["qm"].ravel(), d["vir"].ravel(), d["gtau"].item()
    b, a = butter(4, 20 / 500, "low")      # 20 Hz at 1 kHz sampling
    qf = filtfilt(b, a, q)
    v = np.gradient(qf, t)
    acc = np.gradient(v, t)
    sl = slice(0, None, decimate)
    model = {"name": "emps", "states": ["q", "v"], "inputs": ["vir"], "constants": {"gtau": gtau},
             "parameters": [{"name": "M", "value": 80.0, "lower": 1.0, "unit": "kg"},
                            {"name": "Fv", "value": 100.0, "lower": 0.0, "unit": "N s/m"},
                            {"name": "offset", "value": 0.0, "unit": "N"}],
             "equations": {"q": "v", "v": "(gtau*vir - Fv*v - offset)/M"}}
    exp = {"name": "emps", "time": t[sl].tolist(), "inputs": {"vir": vir[sl].tolist()},
           "outputs": {"q": qf[sl].tolist(), "v": v[sl].tolist()}, "derivatives": {"v": acc[sl].tolist()}}
    return {"model": model, "experiments": [exp], "method": "equation_error"}


EMPS_PULSES = EMPS.parent / "DATA_EMPS_PULSES.mat"


def emps_record(path: Path = EMPS, decimate: int = 10, name: str = "emps") -> dict:
    """The raw encoder position qm and the controller output vir, nothing derived from them, decimated
    to 100 Hz with an anti-alias filter (scipy.signal.decimate, zero phase)."""
    import scipy.io
    from scipy.signal import decimate as decimate_signal
    d = scipy.io.loadmat(path)
    t, q, vir = d["t"].ravel(), d["qm"].ravel(), d["vir"].ravel()
    if decimate > 1:
        q = decimate_signal(q, decimate, ftype="fir", zero_phase=True)
        vir = decimate_signal(vir, decimate, ftype="fir", zero_phase=True)
        t = t[::decimate]
    return {"name": name, "time": t.tolist(), "inputs": {"vir": vir.tolist()}, "outputs": {"qm": q.tolist()}}


def emps_position_request(decimate: int = 10) -> dict:
    """Output error on the position alone, model declared without Coulomb friction, the pulses
    record as validation."""
    import scipy.io
    gtau = scipy.io.loadmat(EMPS)["gtau"].item()
    model = {"name": "emps", "states": ["q", "v"], "inputs": ["vir"], "constants": {"gtau": gtau},
             "parameters": [{"name": "M", "value": 80.0, "lower": 1.0, "unit": "kg"},
                            {"name": "Fv", "value": 100.0, "lower": 0.0, "unit": "N s/m"},
                            {"name": "offset", "value": 0.0, "unit": "N"}],
             "equations": {"q": "v", "v": "(gtau*vir - Fv*v - offset)/M"}, "outputs": {"qm": "q"}}
    return {"model": model, "experiments": [emps_record(EMPS, decimate, "estimation")],
            "validation": [emps_record(EMPS_PULSES, decimate, "pulses")], "method": "multiple_shooting",
            "options": {"substeps": 2}}
