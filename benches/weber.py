#!/usr/bin/env python3
"""What the §4.3 Weber-fraction removal of cache records buys over a long shot.

Renders a job twice with `anchors`, at the same time on one worker thread each (so that both
runs share the machine alike): once as the job says (`weber_threshold` 0.5 by default) and
once with the rule off (`weber_threshold` 0). Prints, every `--every` frames, the records in
the cache, the interpolation and total seconds of each run, and the difference the rule
makes to the image: the RMS of the two runs' indirect light (and of the beauty) against each
other, as a percentage of the rule-off run's mean.

With `--reference-spp N`, also the error each run's indirect light has against the path
tracer's at the printed frames: two path-traced renders of N/2 samples a pixel each, of two
seeds, make the reference (their mean) and measure its own noise (the variance of their
mean, a quarter of their squared difference), which is taken out of each run's squared
error, so that what is left is the run's own RMS error beyond the reference's noise, as a
percentage of the reference's mean. The rule's cost in accuracy is the difference between
the two runs' errors.

    .venv/bin/python benches/weber.py benches/sponza/pushin.json --reference-spp 1024

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
    ap.add_argument(
        "--reference-spp",
        type=int,
        default=0,
        help="path-trace a reference of this many samples a pixel at the printed frames",
    )
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
        printed = [f for f in frames if f % args.every == 0 or f == frames[-1]]
        refs = {}
        if args.reference_spp:
            for k in range(2):
                j = json.loads(json.dumps(job))
                preset = job.get("method", {}).get("preset", "production")
                j["method"] = {
                    "name": "path-trace",
                    "preset": preset,
                    "path_samples": max(args.reference_spp // 2, 1),
                }
                j["seed"] = job.get("seed", 1) + k
                out = os.path.join(tmp, f"reference{k}")
                j["output"] = dict(j.get("output", {}), directory=out)
                path = os.path.join(tmp, f"reference{k}.json")
                json.dump(j, open(path, "w"))
                for f in printed:
                    cmd = [args.bin, "render", "-q", path, "--frames", str(f)]
                    if subprocess.call(cmd, stderr=subprocess.DEVNULL) != 0:
                        sys.exit(f"the reference of frame {f} failed")
                refs[k] = out

        def stats(label, f):
            return json.load(open(os.path.join(runs[label], f"{name}.{f:04d}.json")))

        def exr(label, f):
            return os.path.join(runs[label], f"{name}.{f:04d}.exr")

        ind = ["indirect.R", "indirect.G", "indirect.B"]

        def against_reference(f):
            """Each run's indirect RMS error beyond the reference's noise, and that noise, as
            percentages of the reference's mean."""
            r0, r1 = (read(os.path.join(refs[k], f"{name}.{f:04d}.exr"), ind) for k in range(2))
            ref = 0.5 * (r0 + r1)
            noise = np.mean((r0 - r1) ** 2) / 4.0
            scale = 100.0 / np.mean(np.abs(ref))
            runs = []
            for label in ("on", "off"):
                mse = np.mean((read(exr(label, f), ind) - ref) ** 2) - noise
                runs.append(scale * np.sign(mse) * np.sqrt(abs(mse)))
            return runs[0], runs[1], scale * np.sqrt(noise)

        print(f"{args.job}, frames {frames[0]}-{frames[-1]}, one worker thread per run")
        head = ("| frame | records (rule on) | records (off) | retired by the rule | "
                "interpolation s (on / off) | frame s (on / off) | indirect diff % | beauty diff % |")
        rule = "|---:|---:|---:|---:|---:|---:|---:|---:|"
        if refs:
            head += f" indirect error % against {args.reference_spp} spp (on / off) | reference noise % |"
            rule += "---:|---:|"
        print(head)
        print(rule)
        tot = {"on": [0.0, 0.0], "off": [0.0, 0.0]}
        diffs = []
        errors = []
        for f in frames:
            s_on, s_off = stats("on", f), stats("off", f)
            for label, s in (("on", s_on), ("off", s_off)):
                tot[label][0] += s["timings_s"]["cache_interpolation"]
                tot[label][1] += s["timings_s"]["total"]
            d_ind = rms_pct(read(exr("on", f), ind), read(exr("off", f), ind))
            d_b = rms_pct(read(exr("on", f), "RGB"), read(exr("off", f), "RGB"))
            diffs.append((d_ind, d_b))
            if f in printed:
                line = (
                    f"| {f} | {s_on['counts']['caches']} | {s_off['counts']['caches']} | "
                    f"{s_on['counts']['caches_retired']} | "
                    f"{s_on['timings_s']['cache_interpolation']:.3f} / "
                    f"{s_off['timings_s']['cache_interpolation']:.3f} | "
                    f"{s_on['timings_s']['total']:.2f} / {s_off['timings_s']['total']:.2f} | "
                    f"{d_ind:.2f} | {d_b:.2f} |"
                )
                if refs:
                    e_on, e_off, noise = against_reference(f)
                    errors.append((e_on, e_off))
                    line += f" {e_on:.2f} / {e_off:.2f} | {noise:.2f} |"
                print(line)
        n = len(frames)
        line = (
            f"| all {n} | | | | {tot['on'][0]:.1f} / {tot['off'][0]:.1f} | "
            f"{tot['on'][1]:.1f} / {tot['off'][1]:.1f} | "
            f"{np.mean([d[0] for d in diffs]):.2f} (mean) | {np.mean([d[1] for d in diffs]):.2f} (mean) |"
        )
        if refs:
            line += (
                f" {np.mean([e[0] for e in errors]):.2f} / "
                f"{np.mean([e[1] for e in errors]):.2f} (mean) | |"
            )
        print(line)


if __name__ == "__main__":
    main()
