"""What the benchmark scripts share: EXR channels as arrays, and the error they report."""

import numpy as np
import OpenEXR


def read(path, names):
    """The channels `names` of the EXR at `path`, stacked, as float64."""
    ch = OpenEXR.File(path, separate_channels=True).parts[0].channels
    return np.stack([ch[n].pixels.astype(np.float64) for n in names])


def rms_pct(a, ref):
    """RMS of `a` − `ref` as a percentage of the mean of |`ref`|."""
    return 100.0 * float(np.sqrt(np.mean((a - ref) ** 2)) / max(np.mean(np.abs(ref)), 1e-12))
