"""The trainer's own checks: pair geometry exact against a pure-numpy warp, templates against
PIL's antialiased resize, labels against the formula, a short CPU run whose loss falls, and
export -> reload. Run: `python3 -m pytest training/tests -q` (needs torch, numpy, pillow)."""

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import pairs as P  # noqa: E402
import train as T  # noqa: E402
from tdcm import Tdcm, normalise  # noqa: E402


def textured_photo(width, height, seed):
    """A photo with structure at several scales (no flat areas)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    image = np.zeros((height, width, 3))
    for c in range(3):
        for _ in range(6):
            fx, fy = rng.uniform(-0.5, 0.5, 2)
            phase = rng.uniform(0, 2 * math.pi)
            image[..., c] += np.sin(fx * x + fy * y + phase) * rng.uniform(0.2, 1.0)
    image += rng.normal(0, 0.15, image.shape)
    image = (image - image.min()) / (image.max() - image.min())
    return (image * 255).round().astype(np.uint8)


@pytest.fixture(scope="module")
def bank():
    photos = [textured_photo(300, 260, 1), textured_photo(260, 320, 2), textured_photo(400, 300, 3)]
    return photos, P.PhotoBank(photos, "cpu")


def numpy_bilinear(photo, x, y):
    """`imaging::bilinear_rgb8` (src/imaging/rgb.rs) in float64."""
    h, w = photo.shape[:2]
    x0, y0 = int(math.floor(x)), int(math.floor(y))
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0
    p = photo.astype(np.float64) / 255.0
    top = p[y0, x0] * (1 - fx) + p[y0, x1] * fx
    bottom = p[y1, x0] * (1 - fx) + p[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def test_search_windows_match_a_numpy_warp(bank):
    photos, b = bank
    gen = torch.Generator().manual_seed(7)
    pairs = P.cut_pairs(b, 6, "S2", search_side=96, gen=gen)
    rng = np.random.default_rng(0)
    for k in range(6):
        photo = photos[int(pairs.photos[k])]
        x, y, angle, sx, sy = pairs.truth[k].double().tolist()
        x0, y0, bw, bh = pairs.boxes[k].double().tolist()
        assert abs(sx - bw / 36) < 1e-6 and abs(sy - bh / 36) < 1e-6
        cx, cy = x0 + (bw - 1) / 2, y0 + (bh - 1) / 2
        s, c = math.sin(math.radians(angle)), math.cos(math.radians(angle))
        for i, j in [(0, 0), (95, 95), (0, 95), (95, 0)] + [tuple(rng.integers(0, 96, 2)) for _ in range(40)]:
            p, q = i - x, j - y
            expected = numpy_bilinear(photo, cx + p * c - q * s, cy + p * s + q * c)
            actual = pairs.searches[k, :, j, i].double().numpy()
            np.testing.assert_allclose(actual, expected, atol=2e-5)
        # The object's centre shows the box centre: the pose maps the template centre there.
        centre = pairs.searches[k, :, int(round(y)), int(round(x))]
        assert torch.isfinite(centre).all()


def test_the_bank_samples_as_grid_sample_over_the_whole_photos(bank):
    """PhotoBank.sample reads the uint8 bank tap by tap; grid_sample over a float copy of every
    pair's photo (what the cutter did before) is the reference, inside, at the edges and beyond
    them; PhotoBank.box reads a box exactly, zero beyond the bank."""
    _, b = bank
    gen = torch.Generator().manual_seed(3)
    k, n = 5, 400
    photo = torch.randint(len(b), (k,), generator=gen)
    _, _, h, w = b.pixels.shape
    px = torch.rand((k, n), generator=gen) * (w + 8) - 4
    py = torch.rand((k, n), generator=gen) * (h + 8) - 4
    px[:, :4] = torch.tensor([0.0, w - 1.0, w - 0.5, -0.5])
    py[:, :4] = torch.tensor([0.0, h - 1.0, -0.5, h - 0.5])
    pixels = b.pixels[photo].float() / 255.0
    grid = torch.stack([px / (w - 1) * 2 - 1, py / (h - 1) * 2 - 1], -1)[:, None]
    expected = torch.nn.functional.grid_sample(pixels, grid, mode="bilinear",
                                               padding_mode="zeros", align_corners=True)
    torch.testing.assert_close(b.sample(photo, px, py), expected[:, :, 0], atol=2e-5, rtol=0)
    corners = [(0, 2), (5, 0), (w - 3, 4), (7, h - 2), (1, 9)]  # one per photo, two at the edges
    box = b.box(photo, torch.tensor([x for x, _ in corners]), torch.tensor([y for _, y in corners]),
                6, 4)
    for i, (x0, y0) in enumerate(corners):
        part = pixels[i, :, y0:y0 + 4, x0:x0 + 6]
        torch.testing.assert_close(box[i, :, :part.shape[1], :part.shape[2]], part, atol=1e-6, rtol=0)
        assert box[i, :, part.shape[1]:, :].abs().sum() == 0 and box[i, :, :, part.shape[2]:].abs().sum() == 0


def test_templates_match_pils_antialiased_resize(bank):
    photos, b = bank
    gen = torch.Generator().manual_seed(3)
    pairs = P.cut_pairs(b, 8, "S2.5", search_side=160, gen=gen)
    for k in range(8):
        photo = photos[int(pairs.photos[k])].astype(np.float32) / 255.0
        x0, y0, bw, bh = (int(v) for v in pairs.boxes[k].tolist())
        crop = photo[y0:y0 + bh, x0:x0 + bw]
        for c in range(3):
            expected = np.asarray(Image.fromarray(crop[..., c], mode="F").resize((36, 36), Image.BILINEAR))
            np.testing.assert_allclose(pairs.templates[k, c].numpy(), expected, atol=1e-4)
        assert P.structure(pairs.templates[k:k + 1]).item() >= P.DEFAULT_MIN_STRUCTURE


def test_elongated_pairs_reach_the_aspects_of_real_parts(bank):
    _, b = bank
    gen = torch.Generator().manual_seed(5)
    plain = P.cut_pairs(b, 64, "S1.5", search_side=160, gen=gen)
    elongated = P.cut_pairs(b, 64, "S1.5", search_side=160, gen=gen, elongated_share=1.0,
                            aspect_max=2.5)
    ratio = lambda pairs: pairs.truth[:, 3] / pairs.truth[:, 4]
    # The level alone: both axes in 0.8..1.5, aspect at most 1.875.
    assert (plain.truth[:, 3:5] >= 0.79).all() and (ratio(plain).max() < 1.9)
    # A 28x52 part on the grid (sx 0.73, sy 1.36) and its transpose are now drawn.
    r = ratio(elongated)
    assert (r < 0.6).any() and (r > 1.7).any(), r
    assert (elongated.truth[:, 3:5] >= 0.5 - 1e-6).all() and (elongated.truth[:, 3:5] <= 2.0 + 1e-6).all()
    mean = (elongated.truth[:, 3] * elongated.truth[:, 4]).sqrt()
    assert (mean > 0.78).all() and (mean < 1.52).all()
    # Boxes and truth still agree, and the templates are the boxes squeezed onto the grid.
    assert torch.allclose(elongated.truth[:, 3], elongated.boxes[:, 2] / 36)
    assert torch.allclose(elongated.truth[:, 4], elongated.boxes[:, 3] / 36)
    assert elongated.templates.shape[-2:] == (36, 36)


def test_labels_follow_the_pose():
    truth = torch.tensor([[20.0, 30.0, -120.0, 1.3, 0.8], [32.0, 32.0, 90.0, 2.0, 1.0]])
    maps = P.render_labels(truth, 64, 64)
    heat, valid, sign, cos, sx, sy = maps[0]
    assert heat[30, 20] == 1.0
    assert valid.sum() > 20
    inside = valid > 0
    assert (heat[inside] >= 0.5).all() and (heat[~inside] < 0.5).all()
    assert (sign[inside] == 0).all()
    assert torch.allclose(cos[inside], torch.tensor(-0.5), atol=1e-6)
    assert (sx[inside] == 1.3).all() and (sy[inside] == 0.8).all()
    # +90°, sx = 2: the object's x axis points up, so the Gaussian is long in y (sigma 12 vs 6).
    heat = maps[1, 0]
    assert abs(heat[44, 32].item() - math.exp(-0.5)) < 1e-3
    assert abs(heat[32, 44].item() - math.exp(-2.0)) < 1e-3
    assert maps[1, 2, 32, 32] == 1.0


def test_a_ramp_of_light_spans_its_gains_as_src_train_draws_it():
    """The numbers of jitter.rs's `a_ramp_of_light_spans_its_gains_across_the_image_in_its_
    direction`: a 9x5 grey image of 0.5, gains 0.4 -> 1.2."""
    grey = torch.full((2, 3, 5, 9), 0.5)
    gain = P.light_ramp(grey.shape, torch.tensor([0.0, 0.75 * math.pi]),
                        torch.tensor([0.4, 0.4]), torch.tensor([1.2, 1.2]), "cpu")
    lit = grey * gain
    assert abs(lit[0, 1, 2, 0].item() - 0.2) < 1e-5
    assert abs(lit[0, 1, 0, 8].item() - 0.6) < 1e-5
    assert abs(lit[0, 1, 4, 4].item() - 0.4) < 1e-5
    assert abs(lit[1, 1, 4, 0].item() - 0.6) < 1e-5
    assert abs(lit[1, 1, 0, 8].item() - 0.2) < 1e-5


def test_the_jitter_draws_gammas_ramps_and_noise_at_src_trains_shares():
    """jitter.rs's `over_many_images_...` on a batch: the same measures, the same bounds."""
    gen = torch.Generator().manual_seed(0)
    x = P.jitter(torch.full((2000, 3, 32, 32), 0.5), gen)[:, 0]
    across = (x[:, :, :16].mean(dim=(1, 2)) - x[:, :, 16:].mean(dim=(1, 2))).abs()
    down = (x[:, :16].mean(dim=(1, 2)) - x[:, 16:].mean(dim=(1, 2))).abs()
    ramps = (torch.maximum(across, down) > 0.03).float().mean().item()
    step = (x[:, 7, 1:] - x[:, 7, :-1]).abs().mean(dim=1)
    noisy = (step > 0.01).float().mean().item()
    assert 0.2 < ramps < 0.36, ramps
    assert 0.35 < noisy < 0.55, noisy
    # A gamma moves a flat image's level without spreading it: of the images with no ramp,
    # levels beyond what brightness alone (0.5 +- 0.1) reaches.
    flat = torch.maximum(across, down) < 0.01
    moved = ((x.mean(dim=(1, 2)) - 0.5).abs() > 0.12) & flat
    assert 0.1 < moved.float().sum().item() / flat.float().sum().item() < 0.3
    assert x.min() >= 0.0 and x.max() <= 1.0


def test_crowded_pairs_paste_whole_disjoint_copies_and_label_every_one(bank):
    photos, b = bank
    gen = torch.Generator().manual_seed(11)
    pairs = P.cut_pairs(b, 16, "S1.5", search_side=160, gen=gen, elongated_share=0.5, aspect_max=2.2)
    searches, instances, present = P.add_crowd(b, pairs, 1.0, gen, max_extra=4)
    assert present[:, 0].all() and torch.equal(instances[:, 0], pairs.truth)
    assert present[:, 1:].sum() >= 16, "most crowded pairs should hold extra copies"
    rng = np.random.default_rng(1)
    untouched = torch.ones(searches.shape[0], 160, 160, dtype=torch.bool)
    jj, ii = torch.meshgrid(torch.arange(160.0), torch.arange(160.0), indexing="ij")
    for k in range(16):
        photo = photos[int(pairs.photos[k])]
        x0, y0, bw, bh = pairs.boxes[k].double().tolist()
        cx, cy = x0 + (bw - 1) / 2, y0 + (bh - 1) / 2
        rects = []
        for i in present[k].nonzero().squeeze(1).tolist():
            x, y, angle, sx, sy = instances[k, i].double().tolist()
            w, h = sx * 36, sy * 36
            rects.append(torch.tensor([x, y, angle, w, h], dtype=torch.float32))
            # Whole inside the window.
            a = math.radians(angle)
            ex = (w * abs(math.cos(a)) + h * abs(math.sin(a))) / 2
            ey = (w * abs(math.sin(a)) + h * abs(math.cos(a))) / 2
            assert ex - 1e-3 <= x <= 159 - ex + 1e-3 and ey - 1e-3 <= y <= 159 - ey + 1e-3
            # Near-identical: the pair's scales within 15 % on each axis.
            assert abs(math.log(sx / pairs.truth[k, 3].item())) <= math.log(1 / 0.85) + 1e-4
            if i == 0:
                continue
            s, c = math.sin(a), math.cos(a)
            for u, v in [(0.0, 0.0)] + [tuple(rng.uniform(-0.45, 0.45, 2) * (w, h)) for _ in range(20)]:
                # Template-frame offset (u, v) in screen pixels lands at the pose's point ...
                px, py = x + u * c + v * s, y - u * s + v * c
                qi, qj = int(round(px)), int(round(py))
                du, dv = (qi - x) * c - (qj - y) * s, (qi - x) * s + (qj - y) * c
                if abs(du) > w / 2 - 0.01 or abs(dv) > h / 2 - 0.01:
                    continue
                # ... and shows the box's pixel there (bilinear, as the window's own part).
                expected = numpy_bilinear(photo, cx + du * bw / w, cy + dv * bh / h)
                np.testing.assert_allclose(searches[k, :, qj, qi].double().numpy(), expected, atol=2e-5)
            dx, dy = ii - x, jj - y
            inside = ((dx * c - dy * s).abs() <= w / 2) & ((dx * s + dy * c).abs() <= h / 2)
            untouched[k] &= ~inside
        for i in range(len(rects)):
            for j in range(i + 1, len(rects)):
                assert P._rectangles_apart(rects[i], rects[j], 1.0 - 1e-3), (k, i, j)
    # Outside every pasted copy the window is the photo as cut.
    assert torch.equal(searches[untouched[:, None].expand_as(searches)],
                       pairs.searches[untouched[:, None].expand_as(searches)])
    labels = P.render_labels(instances, 160, 160, present=present)
    for k in range(16):
        for i in present[k].nonzero().squeeze(1).tolist():
            x, y, _, sx, sy = instances[k, i].tolist()
            qi, qj = int(round(x)), int(round(y))
            assert labels[k, 0, qj, qi] > 0.95 and labels[k, 1, qj, qi] == 1.0
            assert labels[k, 4, qj, qi] == pytest.approx(sx) and labels[k, 5, qj, qi] == pytest.approx(sy)
    # One instance per image renders as before; share 0 changes nothing.
    assert torch.equal(P.render_labels(pairs.truth, 160, 160),
                       P.render_labels(instances[:, :1], 160, 160, present=present[:, :1]))
    plain, _, alone = P.add_crowd(b, pairs, 0.0, gen)
    assert torch.equal(plain, pairs.searches) and alone[:, 1:].sum() == 0


def test_a_short_cpu_run_lowers_the_loss(bank, tmp_path):
    photos, _ = bank
    corpus = tmp_path / "corpus"
    corpus.mkdir()
    for i in range(5):
        Image.fromarray(textured_photo(260, 240, 10 + i)).save(corpus / f"p{i}.png")
    out = tmp_path / "run"
    common = ["--corpus", str(corpus), "--batch", "4", "--search-size", "64", "--warmup", "10",
              "--validation-pairs", "8", "--device", "cpu", "--minutes", "10"]
    # 100 steps on one batch: the network and the losses can fit it.
    fit = tmp_path / "fit"
    args = T.parse_args(common + ["--out", str(fit), "--steps", "100", "--lr", "2e-3",
                                  "--log-every", "10", "--validate-every", "1000",
                                  "--overfit-one-batch"])
    assert T.train(args) == 100
    log = (fit / "log.txt").read_text().splitlines()
    losses = [float(line.split(" loss ")[1].split()[0]) for line in log if line.startswith("step ") and " loss " in line]
    assert len(losses) == 10
    # Mean loss of the last ten steps against the first ten.
    assert losses[-1] < 0.6 * losses[0], losses
    # A bounded run on fresh pairs, then resumed: the step count and the schedule continue.
    args = T.parse_args(common + ["--out", str(out), "--steps", "30", "--log-every", "10",
                                  "--validate-every", "10", "--crowd-share", "0.5"])
    assert T.train(args) == 30
    snapshots = tmp_path / "snapshots"
    args = T.parse_args(common + ["--out", str(out), "--steps", "40", "--log-every", "5", "--resume",
                                  "--snapshots", str(snapshots)])
    assert T.train(args) == 40
    log = (out / "log.txt").read_text()
    assert "resumed at step 30 (120 pairs seen)" in log and "step 40/40" in log
    # Every save is also kept under its step: the run's end here.
    assert (snapshots / "weights-step40.pth").read_bytes() == (out / "weights.pth").read_bytes()
    # Beside the weights, what they were trained on, counted to the last save.
    record = json.loads((out / "trained_on.json").read_text())
    assert record["pairs"] == 40 * 4 and record["search_sides"] == [64]


def test_a_fitted_schedule_ends_at_its_floor_by_the_minutes_it_was_given(tmp_path):
    corpus = tmp_path / "corpus"
    corpus.mkdir()
    for i in range(3):
        Image.fromarray(textured_photo(200, 180, 20 + i)).save(corpus / f"p{i}.png")
    out = tmp_path / "run"
    # Far more steps than 30 seconds hold: the re-plan inside the warm-up cuts them to what the
    # measured rate reaches, and the run ends on its last step (not on --minutes) at the floor.
    args = T.parse_args(["--corpus", str(corpus), "--out", str(out), "--batch", "2",
                         "--search-size", "64", "--warmup", "20", "--validation-pairs", "4",
                         "--device", "cpu", "--minutes", "5", "--steps", "1000000",
                         "--lr", "1e-3", "--log-every", "1000000", "--validate-every", "1000000",
                         "--fit-schedule", "0.5"])
    steps = T.train(args)
    log = (out / "log.txt").read_text()
    fitted = int(log.split("-> --steps ")[1].split()[0])
    assert 30 < fitted < 1000000 and steps == fitted, log
    last = [line for line in log.splitlines() if line.startswith(f"step {steps}/{steps} ")]
    assert last and float(last[0].split(" lr ")[1].split()[0]) < 0.1 * 1e-3, log
    with pytest.raises(SystemExit):
        T.parse_args(["--corpus", str(corpus), "--out", str(out), "--minutes", "1",
                      "--fit-schedule", "2"])


def test_the_training_record_says_what_every_pair_and_any_pair_could_be():
    common = ["--corpus", "c", "--out", "o"]
    plain = T.trained_on(T.parse_args(common), 1000)
    assert plain["throughout"] == {"grid_scales": [0.8, 1.5], "aspect_max": 1.5 / 0.8}
    assert plain["seen"] == plain["throughout"]
    assert plain["parts_per_window_max"] == 1 and plain["pairs"] == 1000
    wide = T.trained_on(T.parse_args(common + [
        "--level", "S1.5,S2.5", "--elongated-share", "0.5", "--aspect-max", "3.5",
        "--crowd-share", "0.3", "--crowd-max", "5", "--init-weights", "w.pth"]), 10)
    # Every pair: the range both levels share; some pairs: S2.5's independent axes (aspect 5).
    assert wide["throughout"]["grid_scales"] == [0.8, 1.5]
    assert wide["seen"] == {"grid_scales": [0.5, 2.5], "aspect_max": 5.0}
    assert wide["parts_per_window_max"] == 6
    assert "from w.pth" in wide["runs"][0] and "50 % elongated" in wide["runs"][0]


def test_export_round_trip(tmp_path):
    torch.manual_seed(0)
    model = Tdcm().eval()
    path = tmp_path / "weights.pth"
    T.export_weights(model, path)
    state = torch.load(path, weights_only=True)
    official = (Path(__file__).resolve().parents[2] / "../shared/reference/tdcm-official-keys.txt").resolve()
    if official.is_file():
        keys = {line.split("\t")[0]: line.split("\t")[1] for line in official.read_text().splitlines() if line}
        assert set(keys) == set(state)
        for name, shape in keys.items():
            assert list(state[name].shape) == eval(shape), name
    again = Tdcm().eval()
    again.load_state_dict(state)
    t = normalise(torch.rand(2, 3, 36, 36))
    s = normalise(torch.rand(2, 3, 64, 64))
    with torch.no_grad():
        assert torch.equal(model(t, s), again(t, s))


def write_safetensors(tensors, path):
    """The minimal safetensors writer the test needs (f32 and i64)."""
    import json
    header, blobs, offset = {}, [], 0
    for name, tensor in tensors.items():
        array = tensor.detach().cpu().contiguous().numpy()
        blob = array.tobytes()
        dtype = {np.dtype(np.float32): "F32", np.dtype(np.int64): "I64"}[array.dtype]
        header[name] = {"dtype": dtype, "shape": list(array.shape), "data_offsets": [offset, offset + len(blob)]}
        blobs.append(blob)
        offset += len(blob)
    encoded = json.dumps(header).encode()
    encoded += b" " * (-len(encoded) % 8)
    Path(path).write_bytes(len(encoded).to_bytes(8, "little") + encoded + b"".join(blobs))


def test_init_weights_load_exactly_and_refuse_what_does_not_fit(tmp_path):
    torch.manual_seed(1)
    source = Tdcm().eval()
    state = {k: v for k, v in source.state_dict().items() if not k.endswith("num_batches_tracked")}
    path = tmp_path / "ours.safetensors"
    write_safetensors(state, path)
    torch.manual_seed(2)
    model = Tdcm().eval()
    T.load_init_weights(model, path)
    t = normalise(torch.rand(2, 3, 36, 36))
    s = normalise(torch.rand(2, 3, 64, 64))
    with torch.no_grad():
        assert torch.equal(model(t, s), source(t, s))
    # train.py's and interpolate.py's .pth load alike (a cool-down starts from a mix).
    pth = tmp_path / "ours.pth"
    T.export_weights(source, pth)
    torch.manual_seed(3)
    model = Tdcm().eval()
    T.load_init_weights(model, pth)
    with torch.no_grad():
        assert torch.equal(model(t, s), source(t, s))
    del state["conv1.weight"]
    write_safetensors(state, path)
    with pytest.raises(SystemExit, match="conv1.weight: missing"):
        T.load_init_weights(Tdcm(), path)
    torch.save(state, pth)
    with pytest.raises(SystemExit, match="conv1.weight: missing"):
        T.load_init_weights(Tdcm(), pth)


def test_init_weights_read_what_posematch_exports(tmp_path):
    """`posematch weights export` (Rust) writes what `--init-weights` loads: needs the binary."""
    import shutil
    import subprocess
    root = Path(__file__).resolve().parents[2]
    binary = root / "target/release/posematch"
    if not binary.is_file():
        binary = shutil.which("posematch")
    if not binary:
        pytest.skip("no posematch binary (cargo build --release)")
    path = tmp_path / "default.safetensors"
    subprocess.run([str(binary), "weights", "export", "--out", str(path)], check=True)
    model = Tdcm().eval()
    T.load_init_weights(model, path)
    tensors = T.read_safetensors(path)
    assert torch.equal(model.conv1.weight, tensors["conv1.weight"])


def test_interpolated_weights_lie_between_the_two_runs(tmp_path):
    """interpolate.py: alpha 0 and 1 give the two networks exactly, 0.5 the mean of every
    floating-point tensor; weights of another shape are refused."""
    import interpolate as I
    torch.manual_seed(3)
    base = {k: v.clone() for k, v in Tdcm().state_dict().items()}
    torch.manual_seed(4)
    tuned = {k: v.clone() for k, v in Tdcm().state_dict().items()}
    base_path, tuned_path = tmp_path / "base.pth", tmp_path / "tuned.pth"
    torch.save(base, base_path)
    torch.save(tuned, tuned_path)
    for alpha, expected in ((0.0, base), (1.0, tuned)):
        out = tmp_path / f"mix{alpha}.pth"
        I.main(["--base", str(base_path), "--tuned", str(tuned_path), "--alpha", str(alpha),
                "--out", str(out)])
        mixed = torch.load(out, weights_only=True)
        for k, v in mixed.items():
            if v.is_floating_point():
                assert torch.equal(v, expected[k]), k
    half = I.interpolate(base, tuned, 0.5)
    weight = "conv1.weight"
    assert not torch.equal(base[weight], tuned[weight])
    assert torch.allclose(half[weight], (base[weight] + tuned[weight]) / 2)
    model = Tdcm().eval()
    model.load_state_dict(half)  # a complete, loadable state dict
    bad = dict(base)
    bad[weight] = torch.zeros(1)
    with pytest.raises(SystemExit, match="conv1.weight: shape"):
        I.interpolate(bad, tuned, 0.5)
    with pytest.raises(SystemExit, match="--alpha 1.5"):
        I.interpolate(base, tuned, 1.5)
