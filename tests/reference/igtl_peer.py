#!/usr/bin/env python3
"""An OpenIGTLink peer nobody here wrote (pyigtl, from PyPI) against `librplus-server igtl`.

Usage: igtl_peer.py PORT INPUT.json OUTPUT.json
INPUT: {"batches": [[[x, y, z], ...], ...]} surface points in the bridge's frame (RAS), mm.
Connects to the bridge on 127.0.0.1:PORT as pyigtl's OpenIGTLinkClient, sends each batch as one
POINT message (device "Stylus") and waits for the answer to it: the TRANSFORM
"LIBR_ImageToPhysical" and the POINT "LIBR_Targets". Writes
{"updates": [{"transform": 4x4, "targets": [[x, y, z], ...], "target_names": [...]}, ...]}
(pyigtl's decoding, float32 as received). Exits non-zero when an answer does not come in 120 s.
"""
import json
import sys
import time

import numpy as np
import pyigtl


def main():
    port, inp, out = int(sys.argv[1]), sys.argv[2], sys.argv[3]
    batches = json.load(open(inp))["batches"]
    client = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=port)
    t0 = time.time()
    while not client.is_connected():
        if time.time() - t0 > 30:
            sys.exit("igtl_peer: could not connect to the bridge")
        time.sleep(0.05)
    updates = []
    for k, batch in enumerate(batches):
        msg = pyigtl.PointMessage(
            positions=np.asarray(batch, dtype=np.float32),
            names=[f"p{i}" for i in range(len(batch))],
            device_name="Stylus",
            timestamp=1000.0 + k,
        )
        client.send_message(msg, wait=True)
        tr = client.wait_for_message("LIBR_ImageToPhysical", timeout=120)
        tg = client.wait_for_message("LIBR_Targets", timeout=120)
        if tr is None or tg is None:
            sys.exit(f"igtl_peer: no answer to batch {k} in 120 s")
        updates.append(
            {
                "transform": np.asarray(tr.matrix, dtype=np.float64).tolist(),
                "targets": np.asarray(tg.positions, dtype=np.float64).reshape(-1, 3).tolist(),
                "target_names": list(tg.names),
            }
        )
        print(f"igtl_peer: batch {k}: {len(batch)} points → transform and {len(updates[-1]['targets'])} targets")
    client.stop()
    json.dump({"updates": updates}, open(out, "w"))


if __name__ == "__main__":
    main()
