"""Reads an EXR with the OpenEXR Python bindings (independent of the Rust exr crate) and
prints its header facts and channel data as JSON: {"parts": n, "channels": {name:
{"type": ..., "sum": ..., "pixels": [...row-major floats...]}}}."""
import json, sys

import OpenEXR

f = OpenEXR.File(sys.argv[1], separate_channels=True)
out = {"parts": len(f.parts), "compression": str(f.header()["compression"]), "channels": {}}
for name, ch in f.channels().items():
    px = ch.pixels
    out["channels"][name] = {"type": str(px.dtype), "shape": list(px.shape), "pixels": [float(v) for v in px.reshape(-1)]}
print(json.dumps(out))
