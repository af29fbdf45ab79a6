"""Training pairs cut on the device, by the paper's Algorithm 1 as `src/synth` cuts them.

The photos are decoded once and held on the device as one uint8 tensor; each batch draws boxes,
angles, scales and window positions with a `torch.Generator`, samples every search window
straight from that tensor (`PhotoBank.sample`: bilinear, pixel centres at integers, as
`src/imaging/rgb.rs` reads photos; only the taps a window needs are read, never a float copy
of a pair's whole photo) and cuts every template with an exact antialiased-bilinear resize
(the filter of `fast_image_resize` and PIL that `resize_rgb` uses), rejects what `src/synth` rejects (a box that does not fit, a window with
blank border, a template flatter than `min_structure`), jitters the searches as
`src/train/jitter.rs` does and renders the labels as `src/train/labels.rs` does. No CPU data
loader runs on the hot path.
"""

from dataclasses import dataclass
import math

import torch
import torch.nn.functional as F

# Scale ranges of the paper's levels (src/synth `Level::scale_range`).
LEVELS = {"S1": (1.0, 1.0), "S1.5": (0.8, 1.5), "S2": (0.6, 2.0), "S2.5": (0.5, 2.5)}
# What the scale heads can express (`sigmoid * 1.5 + 0.5`; src/model/tdcm.rs HEAD_SCALE_*).
HEAD_SCALES = (0.5, 2.0)
DEFAULT_MIN_STRUCTURE = 6.0
# src/train/labels.rs
SIGMA_FRACTION = 1.0 / 6.0
VALID_THRESHOLD = 0.5


class PhotoBank:
    """Photos as one zero-padded uint8 tensor [N, 3, Hmax, Wmax] plus each one's size."""

    def __init__(self, photos, device):
        if not photos:
            raise ValueError("no photos: give a corpus folder with at least one image")
        h = max(p.shape[0] for p in photos)
        w = max(p.shape[1] for p in photos)
        bank = torch.zeros((len(photos), 3, h, w), dtype=torch.uint8)
        for i, p in enumerate(photos):
            bank[i, :, : p.shape[0], : p.shape[1]] = torch.from_numpy(p).permute(2, 0, 1)
        self.pixels = bank.to(device)
        # The same pixels channels-last, one row of three per pixel, and a last row of zeros
        # that taps outside the bank read: what `sample` and `box` gather.
        self.rows = torch.cat([self.pixels.permute(0, 2, 3, 1).reshape(-1, 3),
                               torch.zeros((1, 3), dtype=torch.uint8, device=self.pixels.device)])
        self.zero_row = self.rows.shape[0] - 1
        self.sizes = torch.tensor([[p.shape[1], p.shape[0]] for p in photos], device=device)
        self.device = torch.device(device)

    def __len__(self):
        return self.pixels.shape[0]

    def sample(self, photo, px, py):
        """Bilinear RGB in [0, 1] at photo positions (`px`, `py`: [k, ...], pixel centres at
        integers) of photo `photo[k]`, read straight from the uint8 bank: four row gathers of
        the taps a window needs, instead of a float copy of every pair's whole photo (up to
        640x640x3 a pair: what `grid_sample` needs as its input; on the CPU that copy was two
        thirds to three quarters of `cut_pairs`' time). The same numbers as `grid_sample(..., mode="bilinear",
        padding_mode="zeros", align_corners=True)` over the padded bank: a tap outside it reads
        0. Returns [k, 3, ...]."""
        x0 = torch.floor(px)
        y0 = torch.floor(py)
        fx = (px - x0).unsqueeze(-1)
        fy = (py - y0).unsqueeze(-1)
        x0 = x0.long()
        y0 = y0.long()
        photo = photo.view(-1, *([1] * (px.dim() - 1)))
        top = torch.lerp(self._read(photo, x0, y0), self._read(photo, x0 + 1, y0), fx)
        bottom = torch.lerp(self._read(photo, x0, y0 + 1), self._read(photo, x0 + 1, y0 + 1), fx)
        # Channels-last in memory, as the network takes its input on the GPU.
        return (torch.lerp(top, bottom, fy) * (1 / 255.0)).movedim(-1, 1)

    def box(self, photo, x0, y0, width, height):
        """Each photo's pixels in the box (x0, y0, up to `width` x `height`; [k] each), as
        [k, 3, height, width] in [0, 1], zero beyond the bank (one gather, no photo copied)."""
        jj, ii = torch.meshgrid(torch.arange(height, device=self.device),
                                torch.arange(width, device=self.device), indexing="ij")
        x = x0.long().view(-1, 1, 1) + ii
        y = y0.long().view(-1, 1, 1) + jj
        values = self._read(photo.view(-1, 1, 1), x, y)
        return (values * (1 / 255.0)).movedim(-1, 1).contiguous()

    def _read(self, photo, x, y):
        """Pixel (x, y) of photo `photo` (broadcast together; whole pixels) as float 0-255,
        channels last; 0 outside the bank."""
        _, c, h, w = self.pixels.shape
        index = (photo.long() * h + y) * w + x
        index = index.masked_fill((x < 0) | (x >= w) | (y < 0) | (y >= h), self.zero_row)
        return self.rows.index_select(0, index.reshape(-1)).view(*index.shape, c).float()


@dataclass
class Pairs:
    """A batch: RGB in [0, 1] (templates [B,3,th,tw], searches [B,3,S,S]) and truth
    [B, 5] = x, y, angle_deg, scale_x, scale_y in the public pose convention, plus the source
    box (x0, y0, bw, bh) and photo index for checks."""

    templates: torch.Tensor
    searches: torch.Tensor
    truth: torch.Tensor
    boxes: torch.Tensor
    photos: torch.Tensor


def _uniform(n, lo, hi, gen, device):
    return lo + (hi - lo) * torch.rand(n, generator=gen, device=device)


def resize_weights(in_sizes, out_size, span):
    """Antialiased bilinear (triangle filter) weights [M, out_size, span] from `in_sizes[m]`
    source pixels (the first `in_sizes[m]` of `span`) to `out_size`: PIL's and
    fast_image_resize's `Bilinear` convolution."""
    scale = in_sizes.float() / out_size  # [M]
    support = scale.clamp(min=1.0)
    o = torch.arange(out_size, device=in_sizes.device, dtype=torch.float32)
    s = torch.arange(span, device=in_sizes.device, dtype=torch.float32)
    centre = (o[None, :] + 0.5) * scale[:, None]  # [M, out]
    lo = (centre - support[:, None] + 0.5).floor().clamp(min=0)  # PIL: int(center - support + 0.5)
    hi = (centre + support[:, None] + 0.5).floor()
    hi = torch.minimum(hi, in_sizes[:, None].float())
    x = (s[None, None, :] - centre[..., None] + 0.5) / support[:, None, None]
    w = (1.0 - x.abs()).clamp(min=0.0)
    inside = (s[None, None, :] >= lo[..., None]) & (s[None, None, :] < hi[..., None])
    w = w * inside
    return w / w.sum(dim=-1, keepdim=True).clamp(min=1e-12)


def structure(templates):
    """Mean grey-level gradient magnitude per pixel, 0-255 (src/synth `template_structure`)."""
    grey = 0.299 * templates[:, 0] + 0.587 * templates[:, 1] + 0.114 * templates[:, 2]
    gx = grey[:, :-1, 1:] - grey[:, :-1, :-1]
    gy = grey[:, 1:, :-1] - grey[:, :-1, :-1]
    return 255.0 * (gx * gx + gy * gy).sqrt().mean(dim=(1, 2))


def _photo_coords(truth_xy, angle_deg, centre, i, j):
    """Photo position of window pixel (i, j): the box centre plus the window offset from the
    object centre, unrotated (src/synth/sampler.rs `unrotate`)."""
    a = torch.deg2rad(angle_deg)
    s, c = torch.sin(a), torch.cos(a)
    p = i - truth_xy[0]
    q = j - truth_xy[1]
    return centre[0] + p * c - q * s, centre[1] + p * s + q * c


def cut_pairs(bank, batch, level="S1.5", template_size=(36, 36), search_side=224,
              min_structure=DEFAULT_MIN_STRUCTURE, gen=None, max_rounds=50,
              elongated_share=0.0, aspect_max=2.5):
    """`batch` pairs from `bank` (see the module doc). `level` is one level name or a list of
    them (each pair draws one).

    `elongated_share` of the pairs show an elongated part instead: the registered template is
    squeezed onto the square grid while the object keeps its aspect, so on the network's grid
    a 28x52 part has sx 0.73 and sy 1.36 (the matcher resizes frames isotropically, by
    36/sqrt(w*h)). Such a pair draws the geometric mean sqrt(sx*sy) from the level's range and
    the aspect sx/sy log-uniform in [1/aspect_max, aspect_max], within what the scale heads can
    express (HEAD_SCALES). The level ranges alone reach sx/sy 1.9 only at both extremes at once,
    and never sx 0.73 at S1.5."""
    device = bank.device
    tw, th = template_size
    side = float(search_side)
    levels = [level] if isinstance(level, str) else list(level)
    ranges = torch.tensor([LEVELS[name] for name in levels], device=device)
    kept = []
    have = 0
    for _ in range(max_rounds):
        m = max(2 * (batch - have), 16)
        photo = torch.randint(len(bank), (m,), generator=gen, device=device)
        pw = bank.sizes[photo, 0].float()
        ph = bank.sizes[photo, 1].float()
        rng = ranges[torch.randint(len(levels), (m,), generator=gen, device=device)]
        sx = rng[:, 0] + (rng[:, 1] - rng[:, 0]) * torch.rand(m, generator=gen, device=device)
        sy = rng[:, 0] + (rng[:, 1] - rng[:, 0]) * torch.rand(m, generator=gen, device=device)
        elongated = torch.rand(m, generator=gen, device=device) < elongated_share
        if elongated.any():
            mean = torch.exp(torch.log(rng[:, 0]) + (torch.log(rng[:, 1]) - torch.log(rng[:, 0]))
                             * torch.rand(m, generator=gen, device=device))
            aspect = torch.exp(_uniform(m, -math.log(aspect_max), math.log(aspect_max), gen, device))
            sx = torch.where(elongated, mean * aspect.sqrt(), sx)
            sy = torch.where(elongated, mean / aspect.sqrt(), sy)
        bw = torch.round(sx * tw).clamp(min=2.0)
        bh = torch.round(sy * th).clamp(min=2.0)
        ok = (bw + 2 <= pw) & (bh + 2 <= ph)
        lo, hi = HEAD_SCALES
        ok &= ~elongated | ((bw >= lo * tw) & (bw <= hi * tw) & (bh >= lo * th) & (bh <= hi * th))
        angle = _uniform(m, -180.0, 180.0, gen, device)
        a = torch.deg2rad(angle)
        ex = (bw * torch.cos(a).abs() + bh * torch.sin(a).abs()) / 2
        ey = (bw * torch.sin(a).abs() + bh * torch.cos(a).abs()) / 2
        ok &= (2 * ex + 2 <= side) & (2 * ey + 2 <= side)
        x0 = torch.floor(torch.rand(m, generator=gen, device=device) * (pw - bw + 1)).clamp(min=0)
        y0 = torch.floor(torch.rand(m, generator=gen, device=device) * (ph - bh + 1)).clamp(min=0)
        x0 = torch.minimum(x0, (pw - bw).clamp(min=0))
        y0 = torch.minimum(y0, (ph - bh).clamp(min=0))
        centre = (x0 + (bw - 1) / 2, y0 + (bh - 1) / 2)
        xc = ex + (side - 1 - 2 * ex) * torch.rand(m, generator=gen, device=device)
        yc = ey + (side - 1 - 2 * ey) * torch.rand(m, generator=gen, device=device)
        last = side - 1
        for i, j in ((0.0, 0.0), (last, 0.0), (0.0, last), (last, last)):
            px, py = _photo_coords((xc, yc), angle, centre, i, j)
            ok &= (px >= 0) & (py >= 0) & (px <= pw - 1) & (py <= ph - 1)
        idx = ok.nonzero().squeeze(1)
        if idx.numel() == 0:
            continue
        photo, pw, ph, bw, bh, angle = photo[idx], pw[idx], ph[idx], bw[idx], bh[idx], angle[idx]
        x0, y0, xc, yc = x0[idx], y0[idx], xc[idx], yc[idx]
        sx, sy = bw / tw, bh / th
        templates = _cut_templates(bank, photo, x0, y0, bw, bh, tw, th)
        good = structure(templates) >= min_structure
        if not good.any():
            continue
        sel = good.nonzero().squeeze(1)
        templates = templates[sel]
        photo, bw, bh, angle, x0, y0, xc, yc, sx, sy = (
            t[sel] for t in (photo, bw, bh, angle, x0, y0, xc, yc, sx, sy))
        cx, cy = x0 + (bw - 1) / 2, y0 + (bh - 1) / 2
        grid_j, grid_i = torch.meshgrid(
            torch.arange(search_side, device=device, dtype=torch.float32),
            torch.arange(search_side, device=device, dtype=torch.float32), indexing="ij")
        px, py = _photo_coords((xc[:, None, None], yc[:, None, None]), angle[:, None, None],
                               (cx[:, None, None], cy[:, None, None]), grid_i, grid_j)
        searches = bank.sample(photo, px, py)
        truth = torch.stack([xc, yc, angle, sx, sy], dim=1)
        boxes = torch.stack([x0, y0, bw, bh], dim=1)
        kept.append((templates, searches, truth, boxes, photo))
        have += templates.shape[0]
        if have >= batch:
            break
    if have < batch:
        raise RuntimeError(
            f"could place only {have} of {batch} {tw}x{th} templates: use larger photos or "
            "photos with more structure")
    cat = [torch.cat(parts, 0)[:batch] for parts in zip(*kept)]
    return Pairs(*cat)


def _axes(angle_deg):
    """The object's u and v axes on screen (the public pose convention): u = (cos a, -sin a),
    v = (sin a, cos a)."""
    a = torch.deg2rad(angle_deg)
    s, c = torch.sin(a), torch.cos(a)
    return torch.stack([c, -s], -1), torch.stack([s, c], -1)


def _rectangles_apart(a, b, gap):
    """Whether rotated rectangles a and b ([..., 5] = x, y, angle_deg, width, height in screen
    pixels) are at least `gap` pixels apart along one of their four edge normals (the separating
    axis test; touching neighbours with a gap of a pixel pass)."""
    au, av = _axes(a[..., 2])
    bu, bv = _axes(b[..., 2])
    d = b[..., :2] - a[..., :2]
    apart = torch.zeros(d.shape[:-1], dtype=torch.bool, device=d.device)
    for n in (au, av, bu, bv):
        reach_a = (a[..., 3] / 2 * (au * n).sum(-1).abs() + a[..., 4] / 2 * (av * n).sum(-1).abs())
        reach_b = (b[..., 3] / 2 * (bu * n).sum(-1).abs() + b[..., 4] / 2 * (bv * n).sum(-1).abs())
        apart |= (d * n).sum(-1).abs() >= reach_a + reach_b + gap
    return apart


def add_crowd(bank, pairs, share, gen=None, max_extra=5, spread=0.15, tries=12, gap=1.0):
    """Crowded scenes: in `share` of the pairs, 1 to `max_extra` more copies of the same part
    (the photo box the template was cut from), each at its own angle and at the pair's scales
    times a factor in [1 - spread, 1 + spread] per axis (near-identical neighbours), pasted with
    the part's rectangular footprint into the search window wherever it fits whole and lies at
    least `gap` pixels from every other instance (touching neighbours included). The paper's
    industrial scenes hold many identical parts; a network trained on one part per image learns
    to keep one strong peak, and the matcher needs every one.

    Returns `(searches, instances, present)`: the searches with the copies pasted, every
    instance's pose [B, K, 5] (the original first; K = 1 + max_extra, or 1 with share 0: the
    searches themselves, uncopied) and which are there [B, K]."""
    if share <= 0 or max_extra < 1:  # one instance each: nothing to copy or label twice
        alone = torch.ones((pairs.truth.shape[0], 1), dtype=torch.bool, device=pairs.truth.device)
        return pairs.searches, pairs.truth[:, None], alone
    searches = pairs.searches.clone()
    b, _, side, _ = searches.shape
    device = searches.device
    th, tw = pairs.templates.shape[-2:]
    k_all = 1 + max_extra
    instances = torch.zeros((b, k_all, 5), device=device)
    instances[:, 0] = pairs.truth
    present = torch.zeros((b, k_all), dtype=torch.bool, device=device)
    present[:, 0] = True
    crowded = torch.rand(b, generator=gen, device=device) < share
    wanted = torch.randint(1, max_extra + 1, (b,), generator=gen, device=device)
    # Footprints on screen: x, y, angle, width, height.
    rects = torch.zeros((b, k_all, 5), device=device)
    rects[:, 0, :3] = pairs.truth[:, :3]
    rects[:, 0, 3] = pairs.truth[:, 3] * tw
    rects[:, 0, 4] = pairs.truth[:, 4] * th
    lo, hi = HEAD_SCALES
    last = side - 1.0
    for k in range(1, k_all):
        shape = (b, tries)
        factor = lambda: torch.exp(_uniform(b * tries, math.log(1 - spread), math.log(1 + spread),
                                            gen, device)).view(shape)
        sx = (pairs.truth[:, 3:4] * factor()).clamp(lo, hi)
        sy = (pairs.truth[:, 4:5] * factor()).clamp(lo, hi)
        angle = _uniform(b * tries, -180.0, 180.0, gen, device).view(shape)
        w, h = sx * tw, sy * th
        a = torch.deg2rad(angle)
        ex = (w * torch.cos(a).abs() + h * torch.sin(a).abs()) / 2
        ey = (w * torch.sin(a).abs() + h * torch.cos(a).abs()) / 2
        fits = (2 * ex + 2 <= side) & (2 * ey + 2 <= side)
        x = ex + (last - 2 * ex).clamp(min=0) * torch.rand(shape, generator=gen, device=device)
        y = ey + (last - 2 * ey).clamp(min=0) * torch.rand(shape, generator=gen, device=device)
        candidate = torch.stack([x, y, angle, w, h], -1)  # [B, T, 5]
        ok = fits & (crowded & (wanted >= k))[:, None]
        for j in range(k):
            apart = _rectangles_apart(rects[:, j:j + 1].expand(-1, tries, -1), candidate, gap)
            ok &= apart | ~present[:, j:j + 1]
        first = ok.float().argmax(1)
        chosen = ok.any(1)
        pick = candidate[torch.arange(b, device=device), first]
        rects[:, k] = torch.where(chosen[:, None], pick, rects[:, k])
        present[:, k] = chosen
        instances[:, k] = torch.stack([pick[:, 0], pick[:, 1], pick[:, 2], pick[:, 3] / tw,
                                       pick[:, 4] / th], -1) * chosen[:, None]
    rows = present[:, 1:].any(1).nonzero().squeeze(1)
    if rows.numel() == 0:
        return searches, instances, present
    x0, y0, bw, bh = (pairs.boxes[rows, i].view(-1, 1, 1) for i in range(4))
    cx, cy = x0 + (bw - 1) / 2, y0 + (bh - 1) / 2
    # The copies show only the part's box: that box (and a pixel around it, for the bilinear
    # taps) is all of the photo read, not the whole photo per crowded pair.
    _, _, hmax, wmax = bank.pixels.shape
    ox, oy = (x0 - 1).clamp(min=0), (y0 - 1).clamp(min=0)
    span_w, span_h = int(bw.max().item()) + 2, int(bh.max().item()) + 2
    patch = bank.box(pairs.photos[rows], ox.view(-1), oy.view(-1), span_w, span_h)
    jj, ii = torch.meshgrid(torch.arange(side, device=device, dtype=torch.float32),
                            torch.arange(side, device=device, dtype=torch.float32), indexing="ij")
    out = searches[rows]
    for k in range(1, k_all):
        here = present[rows, k]
        if not here.any():
            continue
        r = rects[rows, k]
        x, y, angle, w, h = (r[:, i].view(-1, 1, 1) for i in range(5))
        a = torch.deg2rad(angle)
        s, c = torch.sin(a), torch.cos(a)
        dx, dy = ii - x, jj - y
        u = dx * c - dy * s  # along the object's u axis, screen pixels
        v = dx * s + dy * c
        inside = (u.abs() <= w / 2) & (v.abs() <= h / 2) & here.view(-1, 1, 1)
        px = cx + u * bw / w
        py = cy + v * bh / h
        # As grid_sample over the whole bank with border padding: positions clamped to it.
        px = px.clamp(0, wmax - 1) - ox
        py = py.clamp(0, hmax - 1) - oy
        grid = torch.stack([px / (span_w - 1) * 2 - 1, py / (span_h - 1) * 2 - 1], dim=-1)
        copy = F.grid_sample(patch, grid, mode="bilinear", padding_mode="zeros",
                             align_corners=True)
        out = torch.where(inside[:, None], copy, out)
    searches[rows] = out
    return searches, instances, present


def _cut_templates(bank, photo, x0, y0, bw, bh, tw, th):
    """Box (x0, y0, bw, bh) of each photo `photo[k]` resized to tw x th (antialiased
    bilinear)."""
    span_w = int(bw.max().item())
    span_h = int(bh.max().item())
    # The box's pixels (beyond a narrower box, the photo's next pixels: their weights are 0).
    patch = bank.box(photo, x0, y0, span_w, span_h)  # [k, 3, span_h, span_w]
    wx = resize_weights(bw.long(), tw, span_w)  # [k, tw, span_w]
    wy = resize_weights(bh.long(), th, span_h)  # [k, th, span_h]
    # Horizontal pass then vertical, as the separable convolution does.
    horizontal = torch.einsum("kchs,kos->kcho", patch, wx)
    return torch.einsum("kcho,kph->kcpo", horizontal, wy)


# src/train/jitter.rs's shares and ranges (the camera conditions of issue 41).
GAMMA_SHARE, RAMP_SHARE, BLUR_SHARE, NOISE_SHARE = 0.3, 0.3, 0.3, 0.5
GAMMA_RANGE = (0.5, 2.2)
RAMP_DARK_GAIN, RAMP_BRIGHT_GAIN = (0.4, 0.9), (1.0, 1.3)
MAX_NOISE_SIGMA = 15.0 / 255.0


def light_ramp(shape, direction, dark_gain, bright_gain, device):
    """src/train/jitter.rs `LightRamp`: per image [B, 1, H, W] gains falling linearly from
    `bright_gain` at the image's extreme point towards `direction` (radians, x right, y down)
    to `dark_gain` at the opposite one."""
    b, _, h, w = shape
    yy, xx = torch.meshgrid(torch.arange(h, device=device, dtype=torch.float32),
                            torch.arange(w, device=device, dtype=torch.float32), indexing="ij")
    dx, dy = torch.cos(direction).view(b, 1, 1), torch.sin(direction).view(b, 1, 1)
    extent = (dx.abs() * (w - 1) + dy.abs() * (h - 1)).clamp(min=1.0)
    toward = ((xx - (w - 1) / 2) * dx + (yy - (h - 1) / 2) * dy) / extent + 0.5
    gain = dark_gain.view(b, 1, 1) + (bright_gain - dark_gain).view(b, 1, 1) * toward
    return gain[:, None]


def jitter(searches, gen=None):
    """src/train/jitter.rs, the same steps in the same order: brightness ±0.1, contrast 0.7-1.3
    about the mean; with probability 0.3 a gamma (log-uniform 0.5-2.2, values clamped to [0, 1]
    first); with probability 0.3 light falling linearly across the image in a random direction
    (gain 1.0-1.3 at the bright end, 0.4-0.9 at the dark end); with probability 0.3 a [1 2 1]/4
    blur (clamped borders); with probability 0.5 Gaussian noise of sigma up to 15 grey levels;
    clamped to [0, 1]."""
    b = searches.shape[0]
    device = searches.device
    brightness = _uniform(b, -0.1, 0.1, gen, device).view(b, 1, 1, 1)
    contrast = _uniform(b, 0.7, 1.3, gen, device).view(b, 1, 1, 1)
    mean = searches.mean(dim=(1, 2, 3), keepdim=True)
    x = (searches - mean) * contrast + mean + brightness
    gamma_on = (torch.rand(b, generator=gen, device=device) < GAMMA_SHARE).view(b, 1, 1, 1)
    gamma = torch.exp(_uniform(b, math.log(GAMMA_RANGE[0]), math.log(GAMMA_RANGE[1]), gen,
                               device)).view(b, 1, 1, 1)
    x = torch.where(gamma_on, x.clamp(0.0, 1.0) ** gamma, x)
    ramp_on = (torch.rand(b, generator=gen, device=device) < RAMP_SHARE).view(b, 1, 1, 1)
    gain = light_ramp(x.shape, _uniform(b, 0.0, 2 * math.pi, gen, device),
                      _uniform(b, *RAMP_DARK_GAIN, gen, device),
                      _uniform(b, *RAMP_BRIGHT_GAIN, gen, device), device)
    x = torch.where(ramp_on, x * gain.to(x.dtype), x)
    blur = (torch.rand(b, generator=gen, device=device) < BLUR_SHARE).view(b, 1, 1, 1)
    kernel = torch.tensor([0.25, 0.5, 0.25], device=device, dtype=x.dtype)
    c = x.shape[1]
    blurred = F.conv2d(F.pad(x, (1, 1, 0, 0), mode="replicate"),
                       kernel.view(1, 1, 1, 3).repeat(c, 1, 1, 1), groups=c)
    blurred = F.conv2d(F.pad(blurred, (0, 0, 1, 1), mode="replicate"),
                       kernel.view(1, 1, 3, 1).repeat(c, 1, 1, 1), groups=c)
    x = torch.where(blur, blurred, x)
    noisy = (torch.rand(b, generator=gen, device=device) < NOISE_SHARE).view(b, 1, 1, 1)
    sigma = _uniform(b, 0.0, MAX_NOISE_SIGMA, gen, device).view(b, 1, 1, 1)
    noise = torch.randn(x.shape, generator=gen, device=device, dtype=x.dtype)
    x = x + noisy * sigma * noise
    return x.clamp(0.0, 1.0)


def render_labels(truth, width, height, template_size=(36, 36), present=None):
    """src/train/labels.rs: [B, 6, H, W] = heatmap, valid, sign, cos, scale_x, scale_y for
    `truth` [B, 5] (one instance per image) or [B, K, 5] with `present` [B, K] (crowded scenes:
    the heatmap is the maximum over instances and each pixel's parameters are its strongest
    instance's, as there). The Gaussian is drawn only inside the same square window as there
    (3.5 sigma x the larger scale), so the maps agree to rounding."""
    if truth.dim() == 2:
        truth = truth[:, None]
    if present is None:
        present = torch.ones(truth.shape[:2], dtype=torch.bool, device=truth.device)
    device = truth.device
    tw, th = template_size
    sigma_u, sigma_v = tw * SIGMA_FRACTION, th * SIGMA_FRACTION
    jj, ii = torch.meshgrid(torch.arange(height, device=device, dtype=torch.float32),
                            torch.arange(width, device=device, dtype=torch.float32),
                            indexing="ij")
    heat = torch.zeros((truth.shape[0], height, width), device=device)
    params = torch.zeros((truth.shape[0], 4, height, width), device=device)
    for k in range(truth.shape[1]):
        x, y, angle, sx, sy = (truth[:, k, i].view(-1, 1, 1) for i in range(5))
        a = torch.deg2rad(angle)
        s, c = torch.sin(a), torch.cos(a)
        sxc, syc = sx.clamp(min=1e-3), sy.clamp(min=1e-3)
        reach = 3.5 * max(sigma_u, sigma_v) * torch.maximum(sxc, syc)
        x0 = torch.floor(x - reach).clamp(min=0)
        y0 = torch.floor(y - reach).clamp(min=0)
        x1 = torch.ceil(x + reach).clamp(max=width - 1)
        y1 = torch.ceil(y + reach).clamp(max=height - 1)
        window = (ii >= x0) & (ii <= x1) & (jj >= y0) & (jj <= y1)
        dx, dy = ii - x, jj - y
        u = (c * dx - s * dy) / sxc
        v = (s * dx + c * dy) / syc
        g = torch.exp(-0.5 * ((u / sigma_u) ** 2 + (v / sigma_v) ** 2)) * window
        g = g * present[:, k].view(-1, 1, 1)
        stronger = g > heat
        heat = torch.where(stronger, g, heat)
        own = torch.stack([(angle > 0).float().expand_as(g), c.expand_as(g), sx.expand_as(g),
                           sy.expand_as(g)], 1)
        params = torch.where(stronger[:, None], own, params)
    valid = (heat >= VALID_THRESHOLD).float()
    return torch.cat([heat[:, None], valid[:, None], valid[:, None] * params], dim=1)


def losses(maps, labels, eps=1e-6):
    """src/train/loss.rs: centre = BCE against the soft label inside the valid region and
    -log(1 - p) outside, sign cross-entropy and L1 on cos and both scales inside it; each summed
    and divided by the number of valid pixels. Returns (total, dict of terms)."""
    maps = maps.float()
    score, sign, cos, scale_x, scale_y = (maps[:, k:k + 1] for k in range(5))
    heat, valid, t_sign, t_cos, t_sx, t_sy = (labels[:, k:k + 1] for k in range(6))
    positives = valid.sum().clamp(min=1.0)
    p = score.clamp(eps, 1 - eps)
    bce = -(heat * p.log() + (1 - heat) * (1 - p).log())
    negative = -(1 - p).log()
    centre = (valid * bce + (1 - valid) * negative).sum() / positives
    q = sign.clamp(eps, 1 - eps)
    sign_ce = -(t_sign * q.log() + (1 - t_sign) * (1 - q).log())
    sign_term = (valid * sign_ce).sum() / positives

    def l1(pred, target):
        return (valid * (pred - target).abs()).sum() / positives

    terms = {"centre": centre, "sign": sign_term, "cos": l1(cos, t_cos),
             "scale_x": l1(scale_x, t_sx), "scale_y": l1(scale_y, t_sy)}
    return sum(terms.values()), terms


def peak_hits(maps, truth, radius=3.0):
    """Share of images whose score-map arg-max lies within `radius` px of the true centre."""
    score = maps[:, 0]
    b, h, w = score.shape
    flat = score.reshape(b, -1).argmax(dim=1)
    row = (flat // w).float()
    col = (flat % w).float()
    dist = torch.hypot(col - truth[:, 0], row - truth[:, 1])
    return (dist <= radius).float().mean().item()


def learning_rate(step, total, peak, warmup):
    """Linear warm-up, then cosine from `peak` down to 5 % of it (as src/train)."""
    if step < warmup:
        return peak * (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return peak * (0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * progress)))
