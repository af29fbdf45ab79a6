"""Writes the fixture that proves, in CI and without PyTorch, that this trainer trains the network
we serve: `tests/trainer_fixture.rs` loads `fixtures/trainer-weights.pth` through
`posematch`'s importer, runs our burn network on the inputs stored in
`fixtures/trainer-fixture.safetensors` and compares its five maps with this model's, and renders
`src/train/labels.rs`'s labels for the stored poses and compares them with `pairs.render_labels`.

The weights are this trainer's random initialisation with every parameter and BatchNorm
statistic perturbed, so that no layer is the identity or zero (GRN starts at zero). Run from the
repository root after changing the model, the labels or the export:

    python3 training/export_fixture.py
"""

import json
import struct
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import pairs as P  # noqa: E402
from tdcm import Tdcm, normalise  # noqa: E402
from train import export_weights  # noqa: E402

FIXTURES = Path(__file__).resolve().parent / "fixtures"


def write_safetensors(tensors, path, metadata=None):
    """Minimal safetensors writer (float32 only): 8-byte header length, JSON header, data."""
    header, blobs, offset = {}, [], 0
    for name, array in tensors.items():
        data = np.ascontiguousarray(array, dtype="<f4").tobytes()
        header[name] = {"dtype": "F32", "shape": list(array.shape),
                        "data_offsets": [offset, offset + len(data)]}
        blobs.append(data)
        offset += len(data)
    if metadata:
        header["__metadata__"] = metadata
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)
    with open(path, "wb") as f:
        f.write(struct.pack("<Q", len(text)))
        f.write(text)
        for blob in blobs:
            f.write(blob)


def perturbed_model(seed=0):
    torch.manual_seed(seed)
    model = Tdcm()
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.endswith("grn.weight") or name.endswith("grn.bias"):
                p.copy_(0.5 * torch.randn_like(p))
            elif p.dim() == 1:
                p.add_(0.1 * torch.randn_like(p))
            else:
                p.add_(0.5 * p.std() * torch.randn_like(p))
        for name, b in model.named_buffers():
            if name.endswith("running_mean"):
                b.copy_(0.1 * torch.randn_like(b))
            elif name.endswith("running_var"):
                b.copy_(0.5 + torch.rand_like(b))
    return model.eval()


def spread_heads(model, template, search, spread=1.5):
    """Rescales each head's last convolution so that its logits on the fixture's input have mean
    0 and std `spread`: the outputs then span their ranges instead of sitting at one value, and
    any difference upstream shows in them."""
    captured = {}
    hooks = [getattr(model, name)[2].register_forward_hook(
        lambda _m, _i, out, name=name: captured.__setitem__(name, out))
        for name in ("conv_score", "conv_sign", "conv_cos", "conv_scale_x", "conv_scale_y")]
    with torch.no_grad():
        model(template, search)
        for name, logits in captured.items():
            conv = getattr(model, name)[2]
            factor = spread / logits.std().clamp(min=1e-6)
            conv.weight.mul_(factor)
            conv.bias.copy_(conv.bias * factor - logits.mean() * factor)
    for hook in hooks:
        hook.remove()


def main():
    FIXTURES.mkdir(exist_ok=True)
    model = perturbed_model()
    gen = torch.Generator().manual_seed(1)
    template = normalise(torch.rand(1, 3, 36, 36, generator=gen))
    search = normalise(torch.rand(1, 3, 64, 64, generator=gen))
    spread_heads(model, template, search)
    export_weights(model, FIXTURES / "trainer-weights.pth")
    with torch.no_grad():
        maps = model(template, search)
    for k, name in enumerate(("score", "sign", "cos", "scale_x", "scale_y")):
        print(f"{name}: {maps[0, k].min():.3f} .. {maps[0, k].max():.3f}, std {maps[0, k].std():.3f}")
    poses = torch.tensor([
        [20.0, 30.0, -120.0, 1.3, 0.8],
        [31.5, 24.25, 90.0, 2.0, 1.0],
        [40.7, 41.2, 37.5, 0.85, 1.45],
        [3.0, 45.0, 179.0, 1.0, 1.0],  # clipped by the border
    ])
    labels = P.render_labels(poses, 48, 48)
    write_safetensors({
        "template": template.numpy(), "search": search.numpy(), "maps": maps.numpy(),
        "label_poses": poses.numpy(), "labels": labels.numpy(),
    }, FIXTURES / "trainer-fixture.safetensors",
        metadata={"labels": "heatmap, valid, sign, cos, scale_x, scale_y at 48x48, template 36x36",
                  "torch": torch.__version__})
    print(f"wrote {FIXTURES}/trainer-weights.pth and trainer-fixture.safetensors "
          f"(maps in [{maps.min():.3f}, {maps.max():.3f}])")


if __name__ == "__main__":
    main()
