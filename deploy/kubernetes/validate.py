#!/usr/bin/env python3
"""Validates the Kubernetes manifests offline: renders `base/` and the `tls/` overlay and checks
every resource against the Kubernetes JSON schemas bundled in `kubernetes-validate` (strict:
unknown fields fail).

    pip install kubernetes-validate && python3 deploy/kubernetes/validate.py

Rendering uses `kubectl kustomize` when kubectl is installed; otherwise a small renderer that
understands what these kustomizations use (resources, common labels, strategic-merge patches
whose lists merge by `name` and whose nulls delete), so CI needs no kubectl.
"""

import copy
import os
import shutil
import subprocess
import sys

import kubernetes_validate
import yaml

HERE = os.path.dirname(os.path.abspath(__file__))
KUBERNETES_VERSION = "1.32"


def merge(base, patch):
    """Strategic merge as kustomize applies it to these manifests."""
    if isinstance(base, dict) and isinstance(patch, dict):
        out = dict(base)
        for key, value in patch.items():
            if value is None:
                out.pop(key, None)
            elif key in out:
                out[key] = merge(out[key], value)
            else:
                out[key] = copy.deepcopy(value)
        return out
    if isinstance(base, list) and isinstance(patch, list):
        if all(isinstance(x, dict) and "name" in x for x in base + patch):
            out = [copy.deepcopy(x) for x in base]
            for item in patch:
                same = [i for i, x in enumerate(out) if x["name"] == item["name"]]
                if same:
                    out[same[0]] = merge(out[same[0]], item)
                else:
                    out.append(copy.deepcopy(item))
            return out
        return copy.deepcopy(patch)
    return copy.deepcopy(patch)


def render_here(directory):
    with open(os.path.join(directory, "kustomization.yaml")) as f:
        kustomization = yaml.safe_load(f)
    documents = []
    for resource in kustomization.get("resources", []):
        path = os.path.join(directory, resource)
        if os.path.isdir(path):
            documents.extend(render_here(path))
        else:
            with open(path) as f:
                documents.extend(d for d in yaml.safe_load_all(f) if d)
    for entry in kustomization.get("labels", []):
        for document in documents:
            document.setdefault("metadata", {}).setdefault("labels", {}).update(entry["pairs"])
    for entry in kustomization.get("patches", []):
        with open(os.path.join(directory, entry["path"])) as f:
            patch = yaml.safe_load(f)
        targets = [
            i
            for i, d in enumerate(documents)
            if d["kind"] == patch["kind"] and d["metadata"]["name"] == patch["metadata"]["name"]
        ]
        if len(targets) != 1:
            sys.exit(f"{entry['path']}: patches {len(targets)} resources, expected 1")
        documents[targets[0]] = merge(documents[targets[0]], patch)
    return documents


def render(directory):
    if shutil.which("kubectl"):
        text = subprocess.run(
            ["kubectl", "kustomize", directory], check=True, capture_output=True, text=True
        ).stdout
        return [d for d in yaml.safe_load_all(text) if d]
    return render_here(directory)


def main():
    documents = []
    for name in ["base", "tls"]:
        documents += [(name, d) for d in render(os.path.join(HERE, name))]
    with open(os.path.join(HERE, "base", "secret.yaml")) as f:
        documents += [("base/secret.yaml", d) for d in yaml.safe_load_all(f) if d]
    failed = 0
    for origin, document in documents:
        what = f"{origin}: {document['kind']}/{document['metadata']['name']}"
        try:
            kubernetes_validate.validate(document, KUBERNETES_VERSION, strict=True)
            print(f"valid   {what}")
        except kubernetes_validate.ValidationError as e:
            failed += 1
            print(f"INVALID {what}: {'.'.join(map(str, e.path))}: {e.message}")
    print(f"{len(documents) - failed} of {len(documents)} resources valid (Kubernetes {KUBERNETES_VERSION}, strict)")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
