#!/usr/bin/env python3
"""End-to-end benchmark of `psscan solve` (issue 18): the whole command on a synthetic 16 MP
set, stage by stage, next to the Python peer (scripts/peer_rawpy.py: rawpy + NumPy).

It renders one scene twice (`psscan synth`: the DNG RAW set and the dn16 16-bit PNG set), then
runs, round after round so that every configuration sees the same machine load:
  dng full    `psscan solve DNG` with the defaults
  dng half    `psscan solve DNG --resolution half` (the operator's preview)
  dn16 full   `psscan solve DN16`
  dng cloth   `psscan solve CLOTH` with the defaults: the same scene rendered as a DNG set with
              the relief's cast shadows and the cloth sheen lobe (`synth --shadows --sheen`),
              which a real textile shows and the Lambertian model does not explain. There the
              model test fails at about a quarter of the pixels and the robust fit solves them:
              the plain sets' solve (0.16 % of the pixels escalated at 16 MP) hardly measures
              that path. Not one of issue 18's targets; printed with its share escalated.
  peer        `peer_rawpy.py DNG` (half resolution, one normal PNG), when the Python given by
              --python imports rawpy and numpy; skipped with a note otherwise
Each configuration's figure is the median whole-process wall time over the rounds; its stage
table (report.json "stages", which adds up to the solve's total) is the median run's. Each
psscan configuration is also given as a multiple of its decode stage (the frames' decode alone,
the floor the rest of the command is measured against), and issue 18's three time targets are
printed as met or not met (on the medians), each time target with its rounds' lowest and
highest wall time. Each configuration's line also gives its wall time's range over the rounds
and its median CPU time (user and system seconds of all its threads, from `os.wait4`).

Memory: each run's peak resident set (the child's `ru_maxrss`, from `os.wait4`), its median
over the rounds, and its multiple of the set's decoded frames: every frame of the set (lights
and dark) as its decoder gives it, 16-bit samples, one per pixel for a RAW (CFA) set and three
for a dn16 one (`frames x width x height x samples x 2` bytes, from the manifest). Issue 18
asks for a peak of at most 1.5x that.

Usage: bench_e2e.py [--psscan BIN] [--python PY] [--width W --height H] [--rounds N]
                    [--work DIR] [--keep] [--json] [--dng SET] [--dn16 SET]
                    [--cloth SET | --no-cloth]
(--dng, --dn16 and --cloth time sets rendered before, of the same scene, instead of rendering
them; --no-cloth leaves the cloth set out, whose 16 MP render takes minutes.)
Needs only the Python standard library; the peer needs rawpy and numpy in --python. Not part
of `make test` (it takes minutes and needs a few GiB of disk): `make bench-e2e` runs it.
"""
import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import tomllib

HERE = os.path.dirname(os.path.abspath(__file__))
PEER = os.path.join(HERE, "peer_rawpy.py")


def run(cmd):
    """Runs `cmd`; its wall time, standard output, peak resident set in bytes and CPU time
    (user and system seconds over all its threads). The output goes through files, not pipes,
    so that the child can be reaped with `os.wait4`, whose resource usage is that child's
    alone."""
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        start = time.perf_counter()
        child = subprocess.Popen(cmd, stdout=out, stderr=err)
        _, status, usage = os.wait4(child.pid, 0)
        wall = time.perf_counter() - start
        child.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read().decode(), err.read().decode(errors="replace")
    if child.returncode != 0:
        sys.exit(f"bench_e2e: {' '.join(cmd)} failed ({child.returncode}):\n{stderr}")
    # Linux reports ru_maxrss in KiB.
    return wall, stdout, usage.ru_maxrss * 1024, usage.ru_utime + usage.ru_stime


def decoded_frame_bytes(set_dir):
    """The bytes of a set's frames as decoded: 16-bit samples of every frame (lights and
    dark), one per pixel for a RAW set's CFA and three for a dn16 set's RGB."""
    manifest = tomllib.load(open(os.path.join(set_dir, "manifest.toml"), "rb"))
    image = manifest["image"]
    samples = 1 if image.get("encoding") == "raw" else 3
    return len(manifest["frames"]) * image["width"] * image["height"] * samples * 2


def peer_available(python):
    try:
        probe = subprocess.run([python, "-c", "import rawpy, numpy"], capture_output=True)
    except OSError:
        return False
    return probe.returncode == 0


def synth(psscan, out, encoding, width, height, extra=()):
    wall, _, _, _ = run([psscan, "--quiet", "synth", "--out", out, "--width", str(width),
                   "--height", str(height), "--encoding", encoding, "--force", *extra])
    return wall


def solve(psscan, set_dir, out, extra):
    shutil.rmtree(out, ignore_errors=True)
    wall, stdout, peak, cpu = run([psscan, "--quiet", "solve", set_dir, "--out", out, "--json"]
                                  + extra)
    report = json.loads(stdout)
    solved = report.get("pixels", {}).get("solved")
    escalated = report.get("escalated")
    return {"wall_s": wall, "cpu_s": cpu, "stages": report.get("stages", []),
            "total_s": report.get("timings_s", {}).get("total"), "peak_rss_bytes": peak,
            "escalated_share": escalated / solved if solved and escalated is not None else None}


def peer(python, set_dir, out_png):
    wall, stdout, peak, cpu = run([python, PEER, set_dir, out_png])
    figures = json.loads(stdout.strip().splitlines()[-1])
    stages = [{"stage": k[:-2], "seconds": v} for k, v in figures.items()
              if k.endswith("_s") and k != "total_s"]
    return {"wall_s": wall, "cpu_s": cpu, "stages": stages, "total_s": figures.get("total_s"),
            "peak_rss_bytes": peak}


def median_run(runs):
    walls = [r["wall_s"] for r in runs]
    mid = statistics.median_low(walls)
    chosen = next(r for r in runs if r["wall_s"] == mid)
    peaks = [r["peak_rss_bytes"] for r in runs]
    cpus = [r["cpu_s"] for r in runs]
    return dict(chosen, wall_s=statistics.median(walls), walls_s=walls,
                cpu_s=statistics.median(cpus), cpus_s=cpus,
                peak_rss_bytes=statistics.median(peaks), peaks_rss_bytes=peaks)


def spread_lines(results):
    """Each configuration's wall times over the rounds (lowest to highest) and its median CPU
    time. On a shared virtual machine one binary's wall times on one set can spread by a tenth,
    so a target that close to its limit is met or missed by the machine's load as much as by
    the code; the CPU time (user and system, all threads) is the work the command did, which
    a change to the code changes."""
    lines = []
    for name, r in results.items():
        walls = sorted(r["walls_s"])
        lines.append(f"{name}: wall {walls[0]:.2f} to {walls[-1]:.2f} s over {len(walls)} "
                     f"rounds (median {r['wall_s']:.2f} s); CPU {r['cpu_s']:.2f} s "
                     f"({r['cpu_s'] / r['wall_s']:.2f} cores busy)")
    return lines


def stage_seconds(result, stage):
    return next((row["seconds"] for row in result["stages"] if row["stage"] == stage), None)


def table(results):
    names = list(results)
    stages = []
    for r in results.values():
        for row in r["stages"]:
            if row["stage"] not in stages:
                stages.append(row["stage"])
    width = max([len(s) for s in stages] + [24])
    lines = [f"{'stage (s)':<{width}}" + "".join(f"{n:>12}" for n in names)]
    for stage in stages:
        cells = []
        for r in results.values():
            v = stage_seconds(r, stage)
            cells.append(f"{v:12.3f}" if v is not None else f"{'':>12}")
        lines.append(f"{stage:<{width}}" + "".join(cells))
    for key, label in [("total_s", "total (in-process)"), ("wall_s", "wall (whole process)")]:
        cells = "".join(f"{r[key]:12.3f}" if r.get(key) is not None else f"{'':>12}"
                        for r in results.values())
        lines.append(f"{label:<{width}}" + cells)
    return "\n".join(lines)


# The stage that decodes a configuration's frames: the floor the issue names ("decoding the
# frames alone"), which the rest of the command is measured against.
DECODE_STAGES = {"dng full": "decode", "dng half": "decode", "dn16 full": "decode + linearize",
                 "dng cloth": "decode"}

# The configurations issue 18's targets name.
TARGET_CONFIGS = ("dng full", "dng half", "dn16 full")


# Issue 18's memory target: peak resident set over the decoded frames.
MEMORY_TARGET = 1.5


def memory_ratio(result):
    return result["peak_rss_bytes"] / result["decoded_frame_bytes"]


def targets(results):
    """Issue 18's targets, each with the measured figure and whether it is met (None where a
    figure is missing, e.g. the peer was skipped)."""
    peer_wall = results.get("peer (half)", {}).get("wall_s")
    full = results["dng full"]["wall_s"]
    speedup = peer_wall / full if peer_wall else None

    def wall_target(name, limit):
        walls = results[name]["walls_s"]
        return {"target": f"{name} under {limit:g} s wall", "figure": results[name]["wall_s"],
                "unit": "s", "met": results[name]["wall_s"] < limit,
                "rounds": [min(walls), max(walls)]}

    return [
        {"target": "dng full at least 3x the peer's speed", "figure": speedup,
         "unit": "x", "met": None if speedup is None else speedup >= 3.0},
        wall_target("dng half", 2.0),
        wall_target("dn16 full", 5.0),
    ] + [
        {"target": f"{name} peak memory at most {MEMORY_TARGET}x the decoded frames",
         "figure": memory_ratio(results[name]), "unit": "x",
         "met": memory_ratio(results[name]) <= MEMORY_TARGET}
        for name in TARGET_CONFIGS
    ]


def target_line(t):
    """A target as the text output prints it: met or not, its figure, and for a time target
    its rounds' lowest and highest wall time."""
    verdict = {True: "met", False: "not met", None: "not measured"}[t["met"]]
    if t["figure"] is None:
        return f"target: {t['target']}: {verdict}"
    detail = f"{t['figure']:.2f} {t['unit']}"
    if "rounds" in t:
        low, high = t["rounds"]
        detail += f"; rounds {low:.2f} to {high:.2f} {t['unit']}"
    return f"target: {t['target']}: {verdict} ({detail})"


def floor_lines(results):
    """Each psscan configuration's wall time against its decode stage (`decode_s`)."""
    lines = []
    for name, stage in DECODE_STAGES.items():
        decode = results.get(name, {}).get("decode_s")
        if decode:
            wall = results[name]["wall_s"]
            line = (f"{name}: {wall:.2f} s wall, {wall / decode:.2f}x its '{stage}' "
                    f"stage ({decode:.2f} s)")
            share = results[name].get("escalated_share")
            if share is not None:
                solve_s = stage_seconds(results[name], "solve")
                line += f"; solve stage {solve_s:.2f} s, {100 * share:.2f} % of pixels escalated"
            lines.append(line)
    return lines


def memory_lines(results):
    """Each configuration's median peak resident set, and for psscan's its multiple of the
    set's decoded frames."""
    lines = []
    for name, r in results.items():
        line = f"{name}: peak memory {r['peak_rss_bytes'] / 1e9:.3f} GB"
        if "decoded_frame_bytes" in r:
            line += (f", {memory_ratio(r):.2f}x the decoded frames "
                     f"({r['decoded_frame_bytes'] / 1e9:.3f} GB)")
        lines.append(line)
    return lines


def main():
    root = os.path.dirname(HERE)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--psscan", default=os.path.join(root, "target", "release", "psscan"))
    parser.add_argument("--python", default=sys.executable,
                        help="the Python that runs the peer (needs rawpy and numpy)")
    parser.add_argument("--width", type=int, default=4928)
    parser.add_argument("--height", type=int, default=3264)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--work", help="folder for the sets and outputs (default: a temporary one)")
    parser.add_argument("--keep", action="store_true", help="keep the sets and outputs")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument("--dng", help="an existing DNG set to time instead of rendering one")
    parser.add_argument("--dn16", help="an existing dn16 set to time instead of rendering one")
    parser.add_argument("--cloth", help="an existing DNG set with shadows and sheen to time")
    parser.add_argument("--no-cloth", action="store_true", help="leave the cloth set out")
    args = parser.parse_args()
    if not os.access(args.psscan, os.X_OK):
        sys.exit(f"bench_e2e: {args.psscan} not found: build it first (cargo build --release)")
    work = args.work or tempfile.mkdtemp(prefix="psscan-bench-e2e-")
    os.makedirs(work, exist_ok=True)
    log = sys.stderr
    try:
        dng = args.dng or os.path.join(work, "dng")
        dn16 = args.dn16 or os.path.join(work, "dn16")
        cloth = None if args.no_cloth else args.cloth or os.path.join(work, "cloth")
        sets = [(dng, "dng", args.dng, ()), (dn16, "dn16", args.dn16, ())]
        if cloth:
            sets.append((cloth, "dng", args.cloth, ("--shadows", "--sheen")))
        for path, encoding, given, extra in sets:
            if not given:
                what = " ".join([encoding, *extra])
                print(f"rendering the {args.width}x{args.height} {what} set in {work} ...",
                      file=log)
                synth(args.psscan, path, encoding, args.width, args.height, extra)
        # Each psscan configuration's set and options.
        psscan_configs = {
            "dng full": (dng, []),
            "dng half": (dng, ["--resolution", "half"]),
            "dn16 full": (dn16, []),
        }
        if cloth:
            psscan_configs["dng cloth"] = (cloth, [])
        configs = {name: (lambda o, s=set_dir, e=extra: solve(args.psscan, s, o, e))
                   for name, (set_dir, extra) in psscan_configs.items()}
        note = None
        if peer_available(args.python):
            configs["peer (half)"] = lambda o: peer(args.python, dng, o + ".png")
        else:
            note = f"peer skipped: {args.python} cannot import rawpy and numpy"
            print(note, file=log)
        runs = {name: [] for name in configs}
        for k in range(args.rounds):
            for name, go in configs.items():
                out = os.path.join(work, "out-" + name.replace(" ", "-").replace("(", "")
                                   .replace(")", ""))
                runs[name].append(go(out))
                print(f"round {k + 1}/{args.rounds} {name}: {runs[name][-1]['wall_s']:.2f} s",
                      file=log)
        results = {name: median_run(r) for name, r in runs.items()}
        for name, (set_dir, _) in psscan_configs.items():
            results[name]["decode_s"] = stage_seconds(results[name], DECODE_STAGES[name])
            results[name]["decoded_frame_bytes"] = decoded_frame_bytes(set_dir)
        if args.json:
            print(json.dumps({"width": args.width, "height": args.height,
                              "rounds": args.rounds, "note": note, "results": results,
                              "targets": targets(results)},
                             indent=2))
        else:
            print(table(results))
            if "peer (half)" in results:
                p = results["peer (half)"]["wall_s"]
                for name in ("dng full", "dng half"):
                    print(f"{name}: {p / results[name]['wall_s']:.2f}x the peer's speed")
            for line in spread_lines(results) + floor_lines(results) + memory_lines(results):
                print(line)
            for t in targets(results):
                print(target_line(t))
            if note:
                print(note)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
