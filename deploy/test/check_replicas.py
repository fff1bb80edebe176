#!/usr/bin/env python3
"""Checks a failover run against the uninterrupted one (deploy/test-replicas.sh).

    check_replicas.py REFERENCE.json RUN.json AUDIT_DIR LABEL

REFERENCE.json and RUN.json: `librplus-client replay --json` of the same scenarios, the first
without faults. AUDIT_DIR: every replica's audit database (`*.sqlite`). Checks that every session
of RUN completed, that each one's last answer is the reference's (same SHA-256 of the
protobuf-encoded Registration without its stage timings: `result_sha256`), and that every
answer the client received (acknowledged) is in one replica's audit log (session, client_seq and
the hash of the bytes received, `answer_sha256`). Prints one JSON line of figures.
"""
import glob
import json
import sqlite3
import sys


def main(ref_path, run_path, audit_dir, label):
    ref = json.load(open(ref_path))
    run = json.load(open(run_path))
    key = lambda r: (r["scenario"], r["method"])
    ref_by = {key(r): r for r in ref["results"]}
    problems = []
    acked = set()
    resumed = 0
    equal_steps = compared_steps = 0
    for r in run["results"]:
        k = key(r)
        resumed += r["resumed"]
        if r.get("error") or r.get("status"):
            problems.append(f"{k}: did not complete: {r.get('error') or r.get('status')}")
            continue
        want = ref_by[k]["steps"][-1]["result_sha256"]
        got = r["steps"][-1]["result_sha256"]
        if got != want:
            problems.append(f"{k}: last answer {got[:12]} differs from the reference {want[:12]}")
        by_seq = {s["client_seq"]: s["result_sha256"] for s in ref_by[k]["steps"]}
        for s in r["steps"]:
            acked.add((r["session_id"], s["client_seq"], s["answer_sha256"]))
            if s["client_seq"] in by_seq:
                compared_steps += 1
                equal_steps += by_seq[s["client_seq"]] == s["result_sha256"]
    logged = set()
    dbs = sorted(glob.glob(f"{audit_dir}/*.sqlite"))
    for db in dbs:
        c = sqlite3.connect(db)  # a copy: WAL recovery may write
        for row in c.execute(
            "SELECT session_id, client_seq, answer_sha256 FROM registrations "
            "WHERE session_id IS NOT NULL"
        ):
            logged.add((row[0], row[1], row[2]))
        c.close()
    lost = sorted(acked - logged)
    for x in lost[:5]:
        problems.append(f"acknowledged but in no audit log: session {x[0]} client_seq {x[1]}")
    figures = {
        "run": label,
        "sessions": len(run["results"]),
        "completed": sum(1 for r in run["results"] if not (r.get("error") or r.get("status"))),
        "resumes": resumed,
        "acknowledged_registrations": len(acked),
        "lost": len(lost),
        "audit_logs": len(dbs),
        "last_answer_equal": sum(
            1 for r in run["results"]
            if r["steps"] and r["steps"][-1]["result_sha256"] == ref_by[key(r)]["steps"][-1]["result_sha256"]
        ),
        "answers_equal_per_client_seq": f"{equal_steps}/{compared_steps}",
    }
    print(json.dumps(figures))
    if problems:
        print("\n".join(problems), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:5]))
