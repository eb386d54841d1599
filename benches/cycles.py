#!/usr/bin/env python3
"""Seconds per frame against error: anchorage's methods and presets beside Blender's Cycles.

Renders one frame of a job's shot with Cycles (Debian's `blender`, CPU, no denoiser) at
increasing samples per pixel, with anchorage's path tracer at increasing path samples, and
with `anchors` at each preset and camera-sample count. Every image is scored against its
own renderer's converged image (Cycles and anchorage's path tracer at `--converged` samples):
RMS error of the beauty and of the indirect light (Cycles: its diffuse and glossy indirect
passes times their colour passes; anchorage: the `indirect` AOV), as a percentage of the
converged image's mean. `anchors` renders the frames before the one measured too, so that
its time is a steady frame's of the shot. Prints a table and writes an SVG plot.

    .venv/bin/python benches/cycles.py examples/room/job.json --frame 22 --size 128x96

Blender's glTF importer needs numpy: the script lends it the virtual environment's
(`.ci/run` makes it). Each renderer sees the same glTF files, camera and frame (Blender's
importer maps glTF time t to frame t × fps; its light units differ from anchorage's, which
does not matter here: each image is scored against its own renderer's converged one).
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from exrtools import read, rms_pct

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def layer_matrix(t):
    """A job layer's `transform` as a row-major 4x4 (16 numbers), as anchorage builds it
    (`job::TransformFile::matrix`: translation · rotation · scale, the rotation glam's
    intrinsic XYZ Euler angles, Rx·Ry·Rz); None for none."""
    if not t:
        return None
    x, y, z = np.radians(t.get("rotation_deg") or [0.0, 0.0, 0.0])
    rx = np.array([[1, 0, 0], [0, np.cos(x), -np.sin(x)], [0, np.sin(x), np.cos(x)]])
    ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    rz = np.array([[np.cos(z), -np.sin(z), 0], [np.sin(z), np.cos(z), 0], [0, 0, 1]])
    s = t.get("scale", 1.0)
    m = np.eye(4)
    m[:3, :3] = rx @ ry @ rz @ np.diag(np.broadcast_to(np.asarray(s, float), (3,)))
    m[:3, 3] = t.get("translation") or [0.0, 0.0, 0.0]
    return [float(v) for v in m.flatten()]


def cycles_images(path):
    """Beauty and indirect light of a Cycles multilayer EXR."""
    p = "ViewLayer."
    rgb = lambda pass_: read(path, [f"{p}{pass_}.{c}" for c in "RGB"])  # noqa: E731
    beauty = rgb("Combined")
    indirect = rgb("DiffInd") * rgb("DiffCol") + rgb("GlossInd") * rgb("GlossCol")
    return beauty, indirect


def anchorage_images(path):
    return read(path, ["R", "G", "B"]), read(path, ["indirect.R", "indirect.G", "indirect.B"])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("job")
    ap.add_argument("--frame", type=int, default=22)
    ap.add_argument("--size", default="128x96", help="WxH")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--cycles-samples", default="8,16,32,64,128",
                    help="empty: no Cycles rows and no Cycles reference")
    ap.add_argument("--path-samples", default="16,32,64,128,256",
                    help="empty: no rows of our path tracer (its reference stays)")
    ap.add_argument("--presets", default="draft,production,final")
    ap.add_argument("--anchors-spp", default="16,64", help="camera samples per pixel")
    ap.add_argument("--photons", default="",
                    help="photon counts for the anchors rows (method.photons; "
                         "empty: each preset's own)")
    ap.add_argument("--gather-direct", default="",
                    help="method.gather_direct values for the anchors rows (photons, "
                         "shadow-rays); empty: the job's own")
    ap.add_argument("--steady", type=int, default=3, help="frames anchors renders first")
    ap.add_argument("--converged", type=int, default=2048)
    ap.add_argument("--out", default=os.path.join(ROOT, "benches/render_cycles"))
    ap.add_argument("--bin", default=os.path.join(ROOT, "target/release/anchorage"))
    ap.add_argument("--blender", default="blender")
    args = ap.parse_args()
    width, height = map(int, args.size.split("x"))
    os.makedirs(args.out, exist_ok=True)

    job = json.load(open(args.job))
    base = os.path.dirname(os.path.abspath(args.job))
    for layer in job["scene"]:
        layer["path"] = os.path.normpath(os.path.join(base, layer["path"]))
    layers = [{"path": layer["path"], "matrix": layer_matrix(layer.get("transform"))}
              for layer in job["scene"]]
    env = dict(os.environ)
    site = os.path.join(os.path.dirname(os.path.dirname(sys.executable)), "lib",
                        f"python{sys.version_info.major}.{sys.version_info.minor}", "site-packages")
    env["PYTHONPATH"] = site

    rows = []
    with tempfile.TemporaryDirectory(prefix="anchorage-cycles-") as tmp:
        layers_json = os.path.join(tmp, "layers.json")
        json.dump(layers, open(layers_json, "w"))

        def cycles(samples):
            out = os.path.join(tmp, f"cycles{samples}.exr")
            o = subprocess.run(
                [args.blender, "-b", "--factory-startup", "--python-use-system-env", "--python",
                 os.path.join(ROOT, "benches/cycles_render.py"), "--", out, str(args.frame),
                 str(width), str(height), str(samples), str(args.threads), layers_json],
                env=env, capture_output=True, text=True)
            line = next((l for l in o.stdout.splitlines() if l.startswith("ANCHORAGE: ")), None)
            if o.returncode != 0 or line is None:
                sys.exit(f"blender failed:\n{o.stdout[-2000:]}\n{o.stderr[-2000:]}")
            return json.loads(line[len("ANCHORAGE: "):])["seconds"], out

        def anchorage(label, method, first, extra_method=None, spp=None):
            j = json.loads(json.dumps(job))
            j["resolution"] = [width, height]
            j["method"] = dict(j.get("method", {}), name=method, **(extra_method or {}))
            if spp:
                j["render"] = dict(j.get("render", {}), samples_per_pixel=spp)
            out = os.path.join(tmp, label)
            j["output"] = {"directory": out, "name": "f"}
            path = os.path.join(tmp, f"{label}.json")
            json.dump(j, open(path, "w"))
            o = subprocess.run(
                [args.bin, "render", "-q", "--threads", str(args.threads), "--frames",
                 f"{first}-{args.frame}", path], capture_output=True, text=True)
            if o.returncode != 0:
                sys.exit(f"anchorage failed: {o.stderr}")
            st = json.load(open(os.path.join(out, f"f.{args.frame:04d}.json")))
            return st["timings_s"]["total"], os.path.join(out, f"f.{args.frame:04d}.exr")

        cycles_samples = [int(s) for s in args.cycles_samples.split(",") if s]
        t_ref_c = None
        if cycles_samples:
            print(f"converging Cycles at {args.converged} spp ...", file=sys.stderr)
            t_ref_c, ref_c = cycles(args.converged)
            ref_c = cycles_images(ref_c)
        print(f"converging anchorage's path tracer at {args.converged} ...", file=sys.stderr)
        t_ref_a, ref_a = anchorage("pt_ref", "path-trace", args.frame,
                                   {"path_samples": args.converged})
        ref_a = anchorage_images(ref_a)

        def score(renderer, setting, seconds, images, ref):
            b, i = images
            rows.append((renderer, setting, seconds, rms_pct(b, ref[0]), rms_pct(i, ref[1])))
            print(f"{renderer} {setting}: {seconds:.2f} s", file=sys.stderr)

        for s in cycles_samples:
            t, path = cycles(s)
            score("Cycles", f"{s} spp", t, cycles_images(path), ref_c)
        for s in [int(s) for s in args.path_samples.split(",") if s]:
            t, path = anchorage(f"pt{s}", "path-trace", args.frame, {"path_samples": s})
            score("anchorage path-trace", f"{s} paths/px", t, anchorage_images(path), ref_a)
        first = max(job["frames"]["start"], args.frame - args.steady)
        photons = [int(n) for n in args.photons.split(",") if n] or [None]
        directs = [d for d in args.gather_direct.split(",") if d] or [None]
        for preset in args.presets.split(","):
            for spp in map(int, args.anchors_spp.split(",")):
                for n in photons:
                    for d in directs:
                        method = ({"preset": preset} | ({"photons": n} if n else {})
                                  | ({"gather_direct": d} if d else {}))
                        setting = (f"{preset}, {spp} spp" + (f", {n} photons" if n else "")
                                   + (f", {d}" if d else ""))
                        t, path = anchorage(f"a_{preset}_{spp}_{n}_{d}", "anchors", first,
                                            method, spp)
                        score("anchorage anchors", setting, t, anchorage_images(path), ref_a)

    cycles_ref = (f"Cycles {args.converged} spp ({t_ref_c:.1f} s), " if t_ref_c is not None
                  else "")
    print(f"{args.job}, frame {args.frame}, {width}x{height}, {args.threads} threads; "
          f"references: {cycles_ref}anchorage path-trace "
          f"{args.converged} paths/px ({t_ref_a:.1f} s)")
    print("| renderer | setting | s/frame | beauty RMS % | indirect RMS % |")
    print("|---|---|---:|---:|---:|")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]:.2f} | {r[3]:.2f} | {r[4]:.2f} |")
    svg = os.path.join(args.out, "cycles.svg")
    plot(rows, svg)
    print(f"wrote {svg}")


def plot(rows, path):
    """Seconds per frame (x, log) against RMS error (y, log), beauty and indirect panels."""
    colours = {"Cycles": "#d62728", "anchorage path-trace": "#1f77b4",
               "anchorage anchors": "#2ca02c"}
    w, h, pad = 420, 320, 50
    xs = [r[2] for r in rows]
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{2 * w}" height="{h + 40}" '
             'font-family="sans-serif" font-size="11">']
    for panel, (col, title) in enumerate([(3, "beauty"), (4, "indirect")]):
        ys = [r[col] for r in rows]
        lx0, lx1 = np.log10(min(xs)) - 0.1, np.log10(max(xs)) + 0.1
        ly0, ly1 = np.log10(max(min(ys), 1e-3)) - 0.1, np.log10(max(ys)) + 0.1
        ox = panel * w

        def px(x, y):
            return (ox + pad + (np.log10(x) - lx0) / (lx1 - lx0) * (w - 2 * pad),
                    h - pad + 20 - (np.log10(max(y, 1e-3)) - ly0) / (ly1 - ly0) * (h - 2 * pad))

        parts.append(f'<text x="{ox + w / 2}" y="14" text-anchor="middle">{title}: RMS % against '
                     'each renderer\'s converged image vs seconds per frame (log-log)</text>')
        parts.append(f'<rect x="{ox + pad}" y="{pad - 30}" width="{w - 2 * pad}" '
                     f'height="{h - 2 * pad + 50}" fill="none" stroke="#888"/>')
        for name, c in colours.items():
            pts = [px(r[2], r[col]) for r in rows if r[0] == name]
            if name != "anchorage anchors" and len(pts) > 1:
                d = " ".join(f"{x:.1f},{y:.1f}" for x, y in pts)
                parts.append(f'<polyline points="{d}" fill="none" stroke="{c}"/>')
            for (x, y), r in zip(pts, [r for r in rows if r[0] == name]):
                parts.append(f'<circle cx="{x:.1f}" cy="{y:.1f}" r="3" fill="{c}"><title>'
                             f'{r[0]} {r[1]}: {r[2]:.2f} s, {r[col]:.2f} %</title></circle>')
        for i, (name, c) in enumerate(colours.items()):
            parts.append(f'<text x="{ox + pad + 6}" y="{pad - 14 + 13 * i}" fill="{c}">{name}</text>')
        for v in (0.1, 0.3, 1, 3, 10, 30, 100):
            if lx0 <= np.log10(v) <= lx1:
                x, _ = px(v, 1)
                parts.append(f'<text x="{x:.1f}" y="{h + 34}" text-anchor="middle">{v} s</text>')
            if ly0 <= np.log10(v) <= ly1:
                _, y = px(1, v)
                parts.append(f'<text x="{ox + pad - 4}" y="{y:.1f}" text-anchor="end">{v} %</text>')
    parts.append("</svg>")
    open(path, "w").write("\n".join(parts))


if __name__ == "__main__":
    started = time.time()
    main()
    print(f"({time.time() - started:.0f} s in all)", file=sys.stderr)
