#!/usr/bin/env python3
"""What `anchorage watch` costs after an edit, as a share of a cold frame.

Copies a job and the glTF files of its layers into a temporary directory, starts
`anchorage watch` on the copy, and edits the copies one after the other as a TD would: a
light's intensity doubled (the first KHR_lights_punctual light, else the first emissive
material's strength), a material's base colour (the first non-emissive material), and a
dynamic prim moved (the first mesh node of an animated layer, by 0.5 along z). After each
edit it waits for the watch's log line and prints the rule, seconds, gather rays and the
share of the cold render (the watch's first render of the same frames).

    python3 benches/watch.py examples/room/job.json --frames 0
    python3 benches/watch.py benches/sponza/job.json --frames 0

Binary GLB layers are copied but not edited (the edits go to .gltf layers).
"""

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import queue

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def save(path, doc):
    """An editor's atomic save: a temporary file renamed over the file."""
    tmp = path + ".part"
    with open(tmp, "w") as f:
        json.dump(doc, f)
    os.replace(tmp, path)


def copy_layers(job_path, tmp):
    """The job and its layers (with their external files) copied into `tmp`."""
    job = json.load(open(job_path))
    base = os.path.dirname(os.path.abspath(job_path))
    gltfs = []
    for i, layer in enumerate(job["scene"]):
        src = os.path.normpath(os.path.join(base, layer["path"]))
        sub = os.path.join(tmp, f"layer{i}")
        os.makedirs(sub)
        dst = os.path.join(sub, os.path.basename(src))
        shutil.copy(src, dst)
        if dst.endswith(".gltf"):
            doc = json.load(open(dst))
            for item in doc.get("buffers", []) + doc.get("images", []):
                uri = item.get("uri", "")
                if uri and not uri.startswith("data:"):
                    shutil.copy(os.path.join(os.path.dirname(src), uri), os.path.join(sub, uri))
            gltfs.append(dst)
        layer["path"] = dst
    job["output"] = dict(job.get("output", {}), directory=os.path.join(tmp, "out"))
    path = os.path.join(tmp, "job.json")
    json.dump(job, open(path, "w"))
    return path, gltfs


def edit_light(gltfs):
    for p in gltfs:
        doc = json.load(open(p))
        lights = doc.get("extensions", {}).get("KHR_lights_punctual", {}).get("lights", [])
        if lights:
            lights[0]["intensity"] = 2.0 * lights[0].get("intensity", 1.0)
            save(p, doc)
            return f'light "{lights[0].get("name", 0)}" intensity x2'
    for p in gltfs:
        doc = json.load(open(p))
        for m in doc.get("materials", []):
            s = m.get("extensions", {}).get("KHR_materials_emissive_strength")
            if s:
                s["emissiveStrength"] *= 2.0
                save(p, doc)
                return f'emissive material "{m.get("name")}" strength x2'
    return None


def edit_material(gltfs):
    for p in gltfs:
        doc = json.load(open(p))
        for m in doc.get("materials", []):
            if "emissiveFactor" in m:
                continue
            pbr = m.setdefault("pbrMetallicRoughness", {})
            c = pbr.get("baseColorFactor", [1.0, 1.0, 1.0, 1.0])
            pbr["baseColorFactor"] = [0.5 * c[0], c[1], c[2], c[3]]
            save(p, doc)
            return f'material "{m.get("name")}" base colour red x0.5'
    return None


def edit_dynamic(gltfs):
    for p in gltfs:
        doc = json.load(open(p))
        anims = doc.get("animations", [])
        if not anims:
            continue
        moved = {
            (c["target"].get("node"), c["target"]["path"])
            for a in anims
            for c in a["channels"]
        }
        parent = {c: i for i, n in enumerate(doc["nodes"]) for c in n.get("children", [])}

        def dynamic(i):
            while i is not None:
                n = doc["nodes"][i]
                if n.get("extras", {}).get("motion") == "dynamic" or any(
                        (i, k) in moved for k in ("translation", "rotation", "scale")):
                    return True
                if n.get("extras", {}).get("motion") == "static":
                    return False
                i = parent.get(i)
            return False

        for i, n in enumerate(doc["nodes"]):
            if "mesh" not in n or not dynamic(i):
                continue
            if (i, "translation") in moved:
                # The translation is animated: it stops being, and the node moves.
                for a in anims:
                    keep = [c for c in a["channels"]
                            if (c["target"].get("node"), c["target"]["path"]) != (i, "translation")]
                    used = sorted({c["sampler"] for c in keep})
                    a["samplers"] = [a["samplers"][s] for s in used]
                    for c in keep:
                        c["sampler"] = used.index(c["sampler"])
                    a["channels"] = keep
            t = n.get("translation", [0.0, 0.0, 0.0])
            n["translation"] = [t[0], t[1], t[2] + 0.5]
            save(p, doc)
            return f'dynamic prim "{n.get("name", i)}" moved 0.5 along z'
    return None


LINE = re.compile(r"-> rule (\w+) .*: frames (\S+), ([\d.]+) s, (\d+) gather rays, (\S+ %|-) of")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("job")
    ap.add_argument("--frames", default=None)
    ap.add_argument("--threads", default=None)
    ap.add_argument("--timings", action="store_true",
                    help="also print each re-render's stats timings (first frame)")
    ap.add_argument("--bin", default=os.path.join(ROOT, "target/release/anchorage"))
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="anchorage-watch-bench-") as tmp:
        job, gltfs = copy_layers(args.job, tmp)
        cmd = [args.bin, "watch", "-q", job]
        if args.frames:
            cmd += ["--frames", args.frames]
        if args.threads:
            cmd += ["--threads", args.threads]
        proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
        lines = queue.Queue()
        threading.Thread(target=lambda: [lines.put(l) for l in proc.stderr], daemon=True).start()

        def wait():
            while True:
                l = lines.get(timeout=3600)
                if "error:" in l:
                    sys.exit(f"watch failed: {l}")
                m = LINE.search(l)
                if m:
                    return m

        rows = []
        try:
            m = wait()
            rows.append(("cold render", "(first render)", m))
            for what, edit in [("light", edit_light), ("material", edit_material),
                               ("dynamic prim", edit_dynamic)]:
                done = edit(gltfs)
                if done is None:
                    print(f"# no {what} to edit in {args.job}", file=sys.stderr)
                    continue
                rows.append((done, what, wait()))
                if args.timings:
                    out = os.path.join(tmp, "out")
                    stats = sorted(f for f in os.listdir(out) if f.endswith(".json"))[0]
                    t = json.load(open(os.path.join(out, stats)))["timings_s"]
                    print(what, {k: round(v, 2) for k, v in t.items() if v > 0.005},
                          file=sys.stderr)
        finally:
            proc.terminate()
            proc.wait()
        print(f"{args.job}, frames {rows[0][2].group(2)}:")
        print("| edit | rule | seconds | gather rays | share of a cold frame |")
        print("|---|---|---:|---:|---:|")
        for done, _, m in rows:
            share = "100 %" if done == "cold render" else m.group(5)
            print(f"| {done} | {m.group(1)} | {m.group(3)} | {m.group(4)} | {share} |")


if __name__ == "__main__":
    main()
