"""Shared by the benchmark scripts: memory figures of this process, the views' cameras as the pipeline gets them."""

import time


def vm_mb(key):
    """A ``/proc/self/status`` memory figure in MB (``VmHWM``: peak resident, ``VmRSS``: now); NaN elsewhere."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) / 1024.0
    except OSError:  # not Linux
        pass
    return float("nan")


def session_cameras(session):
    """The views' cameras as the pipeline gets them (calibrated in memory when the session needs it).

    Returns
    -------
    cameras : list of organlab.Camera
    source : str
        Where they came from, for the printout.
    """
    from organlab.calibration import calibration_for

    t0 = time.perf_counter()
    cal, how = calibration_for(session)
    source = {"reused": "from calibration.json", "session.json": "given in session.json"}.get(
        how, f"calibrated from the session's board images ({time.perf_counter() - t0:.1f} s, not written, not timed)")
    return cal.cameras(session), source
