#!/usr/bin/env python3
"""Renders a LIBR+ Kubernetes overlay into plain manifests (docs/deploy.md, "Kubernetes").

    render.py OVERLAY_DIR OUT_DIR

Reads OVERLAY_DIR/kustomization.yaml and writes one file per resource into OUT_DIR
(`KIND-NAME.yaml`, lower case), ready for `kubectl apply -f OUT_DIR`. It understands the subset
of kustomize the manifests here use, with kustomize's meaning, so that `kubectl kustomize`
renders the same objects where a kustomize is installed:

- `resources`: files, or folders holding a kustomization.yaml (rendered first, recursively);
- `namespace`: set on every namespaced object;
- `images`: `name` -> `newName` and/or `newTag`, on every container and init container;
- `patchesStrategicMerge`: files of (multi-document) patches, each matched to one object by
  apiVersion, kind and metadata.name, merged as Kubernetes' strategic merge patch does for the
  fields used here: maps merged key by key (`null` deletes a key), lists of containers, volumes,
  volume mounts, env, ports and the like merged by their merge key (`$patch: delete` removes an
  item), other lists replaced; a whole patch document with `$patch: delete` removes the object.

Anything else in a kustomization.yaml is an error that names it, so that a field this renderer
does not apply is never silently left out.
"""
import copy
import os
import sys

import yaml

KNOWN = {"resources", "namespace", "images", "patchesStrategicMerge"}
# The merge keys of the lists this project's manifests patch (Kubernetes' patchMergeKey).
MERGE_KEYS = {
    "containers": "name",
    "initContainers": "name",
    "volumes": "name",
    "volumeMounts": "mountPath",
    "env": "name",
    "ports": "containerPort",
    "imagePullSecrets": "name",
    "tolerations": None,  # replaced as a whole, as Kubernetes does (no merge key)
}
CLUSTER_SCOPED = {"Namespace", "PriorityClass", "ClusterRole", "ClusterRoleBinding",
                  "StorageClass", "PersistentVolume", "CustomResourceDefinition"}


class RenderError(Exception):
    pass


def load_docs(path):
    with open(path, encoding="utf-8") as f:
        try:
            return [d for d in yaml.safe_load_all(f) if d is not None]
        except yaml.YAMLError as e:
            raise RenderError(f"{path}: not valid YAML: {e}") from e


def key(obj):
    m = obj.get("metadata") or {}
    return (obj.get("apiVersion"), obj.get("kind"), m.get("name"))


def merge(base, patch, field=None):
    """Strategic merge of `patch` into `base` (both plain YAML values); returns the result."""
    if isinstance(patch, dict) and isinstance(base, dict):
        if patch.get("$patch") == "replace":
            return {k: v for k, v in patch.items() if k != "$patch"}
        out = dict(base)
        for k, v in patch.items():
            if k == "$patch":
                continue
            if v is None:
                out.pop(k, None)
            elif k in out:
                out[k] = merge(out[k], v, k)
            else:
                out[k] = strip_directives(v)
        return out
    if isinstance(patch, list) and isinstance(base, list):
        mk = MERGE_KEYS.get(field)
        if mk is None or not all(isinstance(x, dict) for x in base + patch):
            return strip_directives(patch)
        out = [copy.deepcopy(x) for x in base]
        for item in patch:
            if mk not in item:
                raise RenderError(f"a patch item of `{field}` has no `{mk}`: {item}")
            at = next((i for i, x in enumerate(out) if x.get(mk) == item[mk]), None)
            if item.get("$patch") == "delete":
                if at is not None:
                    out.pop(at)
            elif at is None:
                out.append(strip_directives(item))
            else:
                out[at] = merge(out[at], item, None)
        return out
    return strip_directives(patch)


def strip_directives(v):
    if isinstance(v, dict):
        return {k: strip_directives(x) for k, x in v.items() if k != "$patch"}
    if isinstance(v, list):
        return [strip_directives(x) for x in v]
    return copy.deepcopy(v)


def pod_specs(obj):
    """The pod specs inside a workload object."""
    spec = obj.get("spec") or {}
    kind = obj.get("kind")
    if kind == "Pod":
        yield spec
    elif kind == "CronJob":
        yield from pod_specs({"kind": "Job", "spec": spec.get("jobTemplate", {}).get("spec", {})})
    elif "template" in spec:
        yield spec["template"].get("spec") or {}


def set_images(objs, images):
    for img in images:
        name = img.get("name")
        if not name:
            raise RenderError(f"images: an entry has no name: {img}")
        for obj in objs:
            for ps in pod_specs(obj):
                for c in ps.get("containers", []) + ps.get("initContainers", []):
                    ref = c.get("image", "")
                    base = ref.split("@")[0]
                    repo = base.rsplit(":", 1)[0] if ":" in base.split("/")[-1] else base
                    if repo != name:
                        continue
                    tag = base[len(repo) + 1:] if len(base) > len(repo) else None
                    new = img.get("newName", repo)
                    new_tag = img.get("newTag", tag)
                    c["image"] = f"{new}:{new_tag}" if new_tag else new


def render(folder, seen=()):
    folder = os.path.normpath(folder)
    if folder in seen:
        raise RenderError(f"{folder}: kustomizations include each other")
    kpath = os.path.join(folder, "kustomization.yaml")
    if not os.path.isfile(kpath):
        raise RenderError(f"{folder}: no kustomization.yaml")
    docs = load_docs(kpath)
    k = docs[0] if docs else {}
    unknown = sorted(set(k) - KNOWN)
    if unknown:
        raise RenderError(f"{kpath}: fields this renderer does not apply: {', '.join(unknown)}")
    objs = []
    for r in k.get("resources", []):
        p = os.path.join(folder, r)
        if os.path.isdir(p):
            objs += render(p, seen + (folder,))
        elif os.path.isfile(p):
            objs += load_docs(p)
        else:
            raise RenderError(f"{kpath}: resources: {r} does not exist")
    index = {}
    for o in objs:
        if key(o) in index:
            raise RenderError(f"{kpath}: {key(o)} is defined twice")
        index[key(o)] = o
    for pf in k.get("patchesStrategicMerge", []):
        p = os.path.join(folder, pf)
        for patch in load_docs(p):
            kk = key(patch)
            if kk not in index:
                raise RenderError(f"{p}: patches {kk}, which no resource defines")
            at = next(i for i, o in enumerate(objs) if key(o) == kk)
            if patch.get("$patch") == "delete":
                objs.pop(at)
                del index[kk]
                continue
            objs[at] = merge(objs[at], patch)
            index[kk] = objs[at]
    set_images(objs, k.get("images", []))
    ns = k.get("namespace")
    if ns:
        for o in objs:
            if o.get("kind") not in CLUSTER_SCOPED:
                o.setdefault("metadata", {})["namespace"] = ns
    return objs


def main(argv):
    if len(argv) != 3:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    overlay, out = argv[1], argv[2]
    try:
        objs = render(overlay)
    except (RenderError, OSError) as e:
        print(f"render: {e}", file=sys.stderr)
        return 1
    os.makedirs(out, exist_ok=True)
    for f in os.listdir(out):
        if f.endswith(".yaml"):
            os.remove(os.path.join(out, f))
    for o in objs:
        name = f"{o['kind'].lower()}-{o['metadata']['name']}.yaml"
        with open(os.path.join(out, name), "w", encoding="utf-8") as f:
            f.write(f"# Rendered from {overlay} by deploy/k8s/render.sh; do not edit.\n")
            yaml.safe_dump(o, f, sort_keys=False, default_flow_style=False)
    print(f"{len(objs)} objects from {overlay} written to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
