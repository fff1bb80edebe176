#!/usr/bin/env python3
"""How a case's preload (the LIBR basis) grows with the mesh: meshes the liver surface at several
edge lengths with `librplus mesh tetra`, times `librplus bench register --mesh` (cold preload:
loads, assembly, factorization, 75 solves, energy) on each, records the peak memory of each run,
fits the log-log slope and draws time and memory against node count.

    python3 benches/basis_scaling.py --librplus target/release/librplus --out SCALING \
        [--surface assets/livers/sofa_liver.vtk] [--edges 13,10,8,6.5,5.3,4.5,3.8] [--repeat 2] \
        [--coarse-edge 11]

With --coarse-edge, each run also times the basis built on the mesh's boundary meshed again with
tets of that edge and carried to its nodes (`bench register --mesh M --coarse-edge-mm E`: how
soon a case can answer while its own basis builds), as the column `coarse` and a series of the
plot.

Writes SCALING/scaling.csv (one row per run) and, when matplotlib is importable, SCALING/scaling.png.
Peak memory is the child's maximum resident set (Linux `wait4`).
"""
import argparse, csv, json, math, os, re, statistics, subprocess, sys


def run(cmd):
    """Runs `cmd`, returns (stdout, peak RSS in MiB)."""
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out = p.stdout.read()
    _, status, usage = os.wait4(p.pid, 0)
    if os.waitstatus_to_exitcode(status) != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{out}")
    return out, usage.ru_maxrss / 1024.0


def preload(binary, mesh):
    """One cold preload: node count, stage seconds (by the table's header), peak MiB."""
    out, mib = run([binary, "bench", "register", "--mesh", mesh])
    nodes = int(re.search(r"preload: (\d+) nodes", out).group(1))
    lines = out.splitlines()
    head = next(l for l in lines if l.strip().startswith("(s)")).replace("cache read", "cache_read").split()[1:]
    cold = next(l for l in lines if l.strip().startswith("cold")).split()[1:]
    stages = {h: float(v) for h, v in zip(head, cold) if re.fullmatch(r"[0-9.]+", v)}
    return nodes, stages, mib


def coarse(binary, mesh, edge):
    """The coarse basis of `mesh` at `edge` mm: seconds in all (meshing again, basis, carrying)."""
    out, _ = run([binary, "bench", "register", "--mesh", mesh, "--coarse-edge-mm", edge, "--json"])
    line = next(l for l in out.splitlines() if l.startswith("{"))
    c = json.loads(line)["coarse_basis"]
    return c["mesh_s"] + c["basis_s"] + c["transfer_s"]


def slope(xs, ys):
    """Least-squares slope of log y against log x."""
    lx, ly = [math.log(x) for x in xs], [math.log(y) for y in ys]
    mx, my = statistics.fmean(lx), statistics.fmean(ly)
    return sum((a - mx) * (b - my) for a, b in zip(lx, ly)) / sum((a - mx) ** 2 for a in lx)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--librplus", required=True)
    ap.add_argument("--surface", default="assets/livers/sofa_liver.vtk")
    ap.add_argument("--edges", default="13,10,8,6.5,5.3,4.5,3.8")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--out", required=True)
    ap.add_argument("--from-csv", help="plot an earlier run's scaling.csv instead of measuring")
    ap.add_argument("--coarse-edge", help="also time the basis carried from a mesh of this edge (mm)")
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    rows = []
    if a.from_csv:
        with open(a.from_csv) as f:
            rows = [{k: (v if k == "edge_mm" else float(v)) for k, v in r.items()}
                    for r in csv.DictReader(f)]
    for h in [] if a.from_csv else a.edges.split(","):
        mesh = os.path.join(a.out, f"liver_{h}mm.vtu")
        run([a.librplus, "mesh", "tetra", a.surface, "--edge-mm", h, "--out", mesh])
        for r in range(a.repeat):
            nodes, st, mib = preload(a.librplus, mesh)
            if a.coarse_edge:
                st["coarse"] = coarse(a.librplus, mesh, a.coarse_edge)
            rows.append(dict(edge_mm=h, run=r + 1, nodes=nodes, peak_mib=round(mib, 1), **st))
            print(f"edge {h} mm, run {r + 1}: {nodes} nodes, total {st['total']:.3f} s, "
                  f"factor {st['factor']:.3f} s, solve {st['solve']:.3f} s, peak {mib:.0f} MiB",
                  flush=True)
    with open(os.path.join(a.out, "scaling.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    # Medians per mesh, then the slopes (all sizes, and from 10,000 nodes on).
    med = {}
    for r in rows:
        med.setdefault(r["nodes"], []).append(r)
    n = sorted(med)
    keys = ("total", "factor", "solve", "peak_mib") + (("coarse",) if "coarse" in rows[0] else ())
    series = {k: [statistics.median(x[k] for x in med[v]) for v in n] for k in keys}
    for k, ys in series.items():
        big = [(x, y) for x, y in zip(n, ys) if x >= 10000]
        tail = slope(*zip(*big)) if len(big) >= 2 else float("nan")
        print(f"slope of {k}: {slope(n, ys):.2f} over {n[0]}-{n[-1]} nodes, {tail:.2f} from 10,000 on")
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not importable: no plot (the CSV is written)")
        return
    from matplotlib.ticker import FixedLocator, NullFormatter, FuncFormatter
    fig, (ax, am) = plt.subplots(1, 2, figsize=(11, 4.2))
    for k, style in (("total", "o-"), ("factor", "s--"), ("solve", "^:")):
        ax.loglog(n, series[k], style, label=f"{k} (slope {slope(n, series[k]):.2f})")
    if "coarse" in series:
        ax.loglog(n, series["coarse"], "d-", label=f"basis carried from a coarse mesh "
                  f"(slope {slope(n, series['coarse']):.2f})")
    ax.set_xlabel("mesh nodes")
    ax.set_ylabel("cold preload (s)")
    ax.set_title("LIBR basis preload, 75 columns")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    am.loglog(n, series["peak_mib"], "o-", label=f"peak RSS (slope {slope(n, series['peak_mib']):.2f})")
    am.set_xlabel("mesh nodes")
    am.set_ylabel("MiB")
    am.set_title("peak memory of the preload")
    am.grid(True, which="both", alpha=0.3)
    am.legend()
    for axis in (ax, am):
        axis.xaxis.set_major_locator(FixedLocator([2000, 5000, 10000, 20000, 50000]))
        axis.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:,.0f}"))
        axis.xaxis.set_minor_formatter(NullFormatter())
    fig.tight_layout()
    fig.savefig(os.path.join(a.out, "scaling.png"), dpi=110)
    print(f"wrote {os.path.join(a.out, 'scaling.png')}")


if __name__ == "__main__":
    main()
