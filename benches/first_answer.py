#!/usr/bin/env python3
"""How soon an uploaded case answers, against its size: meshes the liver surface at several edge
lengths with `librplus mesh tetra`, starts `librplus-server` on an empty case store with every
upload served from a coarse basis first (`coarse_basis_above_nodes` 1), uploads each mesh with
`librplus-client upload --json` and records, from the start of the upload, when the case was
first READY (on the coarse basis: it answers) and when it was READY on its own basis (and adaptive
LIBR's). Fits the log-log slopes and draws both against node count.

    python3 benches/first_answer.py --bin target/release --out FIRST \
        [--surface assets/livers/sofa_liver.vtk] [--edges 14,10,8,6.5,5.5,4.5,3.7] \
        [--coarse-edge 11]

Writes FIRST/first_answer.csv and, when matplotlib is importable, FIRST/first_answer.png.
"""
import argparse, csv, json, math, os, subprocess, sys, tempfile, time


def slope(xs, ys):
    """Least-squares slope of log y against log x."""
    lx = [math.log(x) for x in xs]
    ly = [math.log(y) for y in ys]
    mx, my = sum(lx) / len(lx), sum(ly) / len(ly)
    num = sum((a - mx) * (b - my) for a, b in zip(lx, ly))
    den = sum((a - mx) ** 2 for a in lx)
    return num / den if den > 0 else float("nan")


def upload(bin_dir, mesh, case_id, coarse_edge, port):
    """One server on an empty store, one upload; the client's JSON summary."""
    with tempfile.TemporaryDirectory() as d:
        cfg = os.path.join(d, "server.json")
        with open(cfg, "w") as f:
            json.dump({"format": 1, "case_store": os.path.join(d, "store"),
                       "coarse_basis_above_nodes": 1, "coarse_basis_edge_mm": coarse_edge,
                       "listen": f"127.0.0.1:{port}", "v2s": False}, f)
        log = open(os.path.join(d, "server.log"), "w+")
        server = subprocess.Popen([os.path.join(bin_dir, "librplus-server"), "--config", cfg],
                                  stdout=log, stderr=subprocess.STDOUT)
        try:
            for _ in range(200):
                log.seek(0)
                if "SERVING" in log.read():
                    break
                time.sleep(0.1)
            out = subprocess.run([os.path.join(bin_dir, "librplus-client"), "upload",
                                  "--server", f"http://127.0.0.1:{port}", "--case", case_id,
                                  "--mesh", mesh, "--json"],
                                 capture_output=True, text=True)
            if out.returncode != 0:
                sys.exit(f"upload of {mesh} failed: {out.stderr}")
            return json.loads(out.stdout)
        finally:
            server.terminate()
            server.wait()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bin", default="target/release", help="folder of librplus, librplus-server, librplus-client")
    ap.add_argument("--out", required=True)
    ap.add_argument("--surface", default="assets/livers/sofa_liver.vtk")
    ap.add_argument("--edges", default="14,10,8,6.5,5.5,4.5,3.7")
    ap.add_argument("--coarse-edge", type=float, default=11.0)
    ap.add_argument("--port", type=int, default=50071)
    ap.add_argument("--from-csv", help="plot an earlier run's first_answer.csv instead of measuring")
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    path = os.path.join(a.out, "first_answer.csv")
    rows = []
    if a.from_csv:
        with open(a.from_csv) as f:
            rows = [{k: float(v) for k, v in r.items()} for r in csv.DictReader(f)]
    else:
        for e in [float(x) for x in a.edges.split(",")]:
            mesh = os.path.join(a.out, f"liver_{e:g}mm.vtu")
            subprocess.run([os.path.join(a.bin, "librplus"), "mesh", "tetra", a.surface,
                            "--edge-mm", f"{e:g}", "--out", mesh], check=True,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            s = upload(a.bin, mesh, f"size-{e:g}", a.coarse_edge, a.port)
            rows.append({"edge_mm": e, "nodes": s["nodes"], "upload_s": s["upload_s"],
                         "first_ready_s": s["first_ready_s"], "ready_s": s["ready_s"]})
            print(f"{e:g} mm: {s['nodes']} nodes, stored {s['upload_s']:.2f} s, answers from "
                  f"{s['first_ready_s']:.2f} s, own basis {s['ready_s']:.2f} s", flush=True)
        with open(path, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    rows.sort(key=lambda r: r["nodes"])
    n = [r["nodes"] for r in rows]
    big = [r for r in rows if r["nodes"] >= 10000]
    for key, name in [("first_ready_s", "first answer"), ("ready_s", "own basis")]:
        if len(big) >= 2:
            print(f"{name}: slope {slope([r['nodes'] for r in big], [r[key] for r in big]):.2f} from 10,000 nodes on")
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not importable: no plot (the CSV is written)")
        return
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    ax.loglog(n, [r["ready_s"] for r in rows], "o-", label="READY on its own basis (and adaptive LIBR's)")
    ax.loglog(n, [r["first_ready_s"] for r in rows], "s-", label=f"first READY: answers (basis carried from {a.coarse_edge:g} mm)")
    ax.loglog(n, [r["upload_s"] for r in rows], "^--", color="grey", label="stored (upload sent and checked)")
    ax.axhline(8.0, color="red", lw=0.8, ls=":", label="8 s")
    from matplotlib.ticker import FixedLocator, NullFormatter, FuncFormatter
    ax.xaxis.set_major_locator(FixedLocator([2000, 5000, 10000, 20000, 50000]))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:,.0f}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("mesh nodes")
    ax.set_ylabel("seconds from the start of the upload")
    ax.set_title("An uploaded liver: time to its first answer and to its own basis")
    ax.grid(True, which="both", lw=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(a.out, "first_answer.png"), dpi=110)
    print(f"wrote {os.path.join(a.out, 'first_answer.png')}")


if __name__ == "__main__":
    main()
