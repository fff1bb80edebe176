#!/usr/bin/env python3
"""Tests of render.py's kustomize subset (run by deploy/check-manifests.sh): what a strategic
merge patch does to maps, keyed lists and plain lists, deletions, images and namespaces, against
expectations written out by hand from Kubernetes' and kustomize's documented behaviour."""
import os
import sys
import tempfile
import textwrap
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import render  # noqa: E402


def write(d, name, text):
    p = os.path.join(d, name)
    os.makedirs(os.path.dirname(p), exist_ok=True)
    with open(p, "w") as f:
        f.write(textwrap.dedent(text))


BASE = """
apiVersion: apps/v1
kind: Deployment
metadata: {name: web, labels: {a: "1"}}
spec:
  replicas: 2
  template:
    spec:
      containers:
        - name: app
          image: librplus
          args: [serve, --x]
          env: [{name: A, value: "1"}, {name: B, value: "2"}]
          volumeMounts: [{name: data, mountPath: /data}]
        - name: side
          image: other:1.0
      volumes: [{name: data, emptyDir: {}}]
---
apiVersion: v1
kind: Namespace
metadata: {name: ns1}
---
apiVersion: policy/v1
kind: PodDisruptionBudget
metadata: {name: web}
spec: {maxUnavailable: 1}
"""


class Render(unittest.TestCase):
    def overlay(self, kustomization, patches=None):
        d = tempfile.mkdtemp()
        write(d, "base/kustomization.yaml", "resources: [all.yaml]\n")
        write(d, "base/all.yaml", BASE)
        write(d, "o/kustomization.yaml", kustomization)
        if patches:
            write(d, "o/patches.yaml", patches)
        return {(o["kind"], o["metadata"]["name"]): o for o in render.render(os.path.join(d, "o"))}

    def test_keyed_lists_merge_plain_lists_replace_and_null_deletes(self):
        objs = self.overlay(
            "resources: [../base]\npatchesStrategicMerge: [patches.yaml]\n",
            """
            apiVersion: apps/v1
            kind: Deployment
            metadata: {name: web, labels: {a: null, b: "2"}}
            spec:
              replicas: 3
              template:
                spec:
                  containers:
                    - name: app
                      args: [serve]
                      env: [{name: B, value: "20"}, {name: C, value: "3"}]
                      volumeMounts: [{name: tls, mountPath: /tls}]
                  volumes: [{name: tls, secret: {secretName: s}}]
            """,
        )
        d = objs[("Deployment", "web")]
        self.assertEqual(d["metadata"]["labels"], {"b": "2"})
        self.assertEqual(d["spec"]["replicas"], 3)
        app, side = d["spec"]["template"]["spec"]["containers"]
        self.assertEqual(side["name"], "side")
        self.assertEqual(app["args"], ["serve"])  # no merge key: replaced
        self.assertEqual(app["env"], [{"name": "A", "value": "1"}, {"name": "B", "value": "20"},
                                      {"name": "C", "value": "3"}])
        self.assertEqual([m["mountPath"] for m in app["volumeMounts"]], ["/data", "/tls"])
        self.assertEqual([v["name"] for v in d["spec"]["template"]["spec"]["volumes"]],
                         ["data", "tls"])

    def test_delete_directives_images_and_namespace(self):
        objs = self.overlay(
            """
            namespace: prod
            resources: [../base]
            patchesStrategicMerge: [patches.yaml]
            images: [{name: librplus, newTag: "1.2"}, {name: other, newName: reg/other}]
            """,
            """
            apiVersion: policy/v1
            kind: PodDisruptionBudget
            metadata: {name: web}
            $patch: delete
            ---
            apiVersion: apps/v1
            kind: Deployment
            metadata: {name: web}
            spec:
              template:
                spec:
                  containers:
                    - {name: app, env: [{name: A, $patch: delete}]}
            """,
        )
        self.assertNotIn(("PodDisruptionBudget", "web"), objs)
        d = objs[("Deployment", "web")]
        app, side = d["spec"]["template"]["spec"]["containers"]
        self.assertEqual(app["image"], "librplus:1.2")
        self.assertEqual(side["image"], "reg/other:1.0")
        self.assertEqual(app["env"], [{"name": "B", "value": "2"}])
        self.assertEqual(d["metadata"]["namespace"], "prod")
        self.assertNotIn("namespace", objs[("Namespace", "ns1")]["metadata"])

    def test_unknown_fields_and_unmatched_patches_are_errors(self):
        with self.assertRaisesRegex(render.RenderError, "commonLabels"):
            self.overlay("resources: [../base]\ncommonLabels: {a: b}\n")
        with self.assertRaisesRegex(render.RenderError, "which no resource defines"):
            self.overlay(
                "resources: [../base]\npatchesStrategicMerge: [patches.yaml]\n",
                "apiVersion: v1\nkind: Service\nmetadata: {name: nope}\n",
            )


if __name__ == "__main__":
    unittest.main()
