#!/usr/bin/env python3
"""What the §4.3 Weber-fraction removal of cache records buys over a long shot.

Renders a job twice with `anchors`, at the same time on one worker thread each (so that both
runs share the machine alike): once as the job says (`weber_threshold` 0.5 by default) and
once with the rule off (`weber_threshold` 0). Prints, every `--every` frames, the records in
the cache, the interpolation and total seconds of each run, and the difference the rule
makes to the image: the RMS of the two runs' indirect light (and of the beauty) against each
other, as a percentage of the rule-off run's mean.

    .venv/bin/python benches/weber.py benches/sponza/pushin.json

(200 frames of a camera pushing into Sponza at 160×90 past the animated box; the OpenEXR and
numpy modules of `.ci/run`'s virtual environment read the frames.)
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

from exrtools import read, rms_pct

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("job")
    ap.add_argument("--frames", help="A-B (default: the job's)")
    ap.add_argument("--every", type=int, default=20, help="print every N-th frame")
    ap.add_argument("--bin", default=os.path.join(ROOT, "target/release/anchorage"))
    args = ap.parse_args()

    job = json.load(open(args.job))
    base = os.path.dirname(os.path.abspath(args.job))
    for layer in job["scene"]:
        layer["path"] = os.path.normpath(os.path.join(base, layer["path"]))
    name = job.get("output", {}).get("name", "frame")
    with tempfile.TemporaryDirectory(prefix="anchorage-weber-") as tmp:
        runs = {}
        procs = []
        for label, threshold in (("on", None), ("off", 0.0)):
            j = json.loads(json.dumps(job))
            method = j.setdefault("method", {"name": "anchors"})
            method["name"] = "anchors"
            if threshold is not None:
                method["weber_threshold"] = threshold
            out = os.path.join(tmp, label)
            j["output"] = dict(j.get("output", {}), directory=out)
            path = os.path.join(tmp, f"{label}.json")
            json.dump(j, open(path, "w"))
            cmd = [args.bin, "render", "-q", "--threads", "1", path]
            if args.frames:
                cmd += ["--frames", args.frames]
            procs.append(subprocess.Popen(cmd, stderr=subprocess.DEVNULL))
            runs[label] = out
        for p in procs:
            if p.wait() != 0:
                sys.exit(f"a render failed (exit {p.returncode})")

        frames = sorted(
            int(f.split(".")[-2])
            for f in os.listdir(runs["off"])
            if f.endswith(".json")
        )

        def stats(label, f):
            return json.load(open(os.path.join(runs[label], f"{name}.{f:04d}.json")))

        def exr(label, f):
            return os.path.join(runs[label], f"{name}.{f:04d}.exr")

        print(f"{args.job}, frames {frames[0]}-{frames[-1]}, one worker thread per run")
        print("| frame | records (rule on) | records (off) | retired by the rule | "
              "interpolation s (on / off) | frame s (on / off) | indirect diff % | beauty diff % |")
        print("|---:|---:|---:|---:|---:|---:|---:|---:|")
        tot = {"on": [0.0, 0.0], "off": [0.0, 0.0]}
        diffs = []
        for f in frames:
            s_on, s_off = stats("on", f), stats("off", f)
            for label, s in (("on", s_on), ("off", s_off)):
                tot[label][0] += s["timings_s"]["cache_interpolation"]
                tot[label][1] += s["timings_s"]["total"]
            ind = ["indirect.R", "indirect.G", "indirect.B"]
            d_ind = rms_pct(read(exr("on", f), ind), read(exr("off", f), ind))
            d_b = rms_pct(read(exr("on", f), "RGB"), read(exr("off", f), "RGB"))
            diffs.append((d_ind, d_b))
            if f % args.every == 0 or f == frames[-1]:
                print(
                    f"| {f} | {s_on['counts']['caches']} | {s_off['counts']['caches']} | "
                    f"{s_on['counts']['caches_retired']} | "
                    f"{s_on['timings_s']['cache_interpolation']:.3f} / "
                    f"{s_off['timings_s']['cache_interpolation']:.3f} | "
                    f"{s_on['timings_s']['total']:.2f} / {s_off['timings_s']['total']:.2f} | "
                    f"{d_ind:.2f} | {d_b:.2f} |"
                )
        n = len(frames)
        print(
            f"| all {n} | | | | {tot['on'][0]:.1f} / {tot['off'][0]:.1f} | "
            f"{tot['on'][1]:.1f} / {tot['off'][1]:.1f} | "
            f"{np.mean([d[0] for d in diffs]):.2f} (mean) | {np.mean([d[1] for d in diffs]):.2f} (mean) |"
        )


if __name__ == "__main__":
    main()
