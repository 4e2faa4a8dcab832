"""The speed/accuracy plot of :func:`garmentnerf.perf.preset_bench.preset_benchmark`'s results (PIL;
matplotlib is not needed)."""

from __future__ import annotations

import math
from pathlib import Path

from PIL import Image, ImageDraw

from garmentnerf.io_utils import atomic_write_path

__all__ = ["write_plot"]


def write_plot(results: dict, path, overwrite: bool = True) -> Path:
    """ms/frame (log x) against PSNR (or points per frame without ground truth), one labelled
    point per preset, as a PNG drawn with PIL."""
    rows = [r for r in results["presets"] if r["ms_per_frame"]]
    use_psnr = all(r["psnr"] is not None for r in rows)
    ys = [r["psnr"] if use_psnr else math.log10(max(r["points_per_frame"], 1)) for r in rows]
    xs = [math.log10(r["ms_per_frame"]) for r in rows]
    W, H, ml, mr, mt, mb = 720, 480, 80, 30, 50, 60
    img = Image.new("RGB", (W, H), "white")
    d = ImageDraw.Draw(img)
    x0, x1 = math.floor(min(xs) * 10) / 10 - 0.1, math.ceil(max(xs) * 10) / 10 + 0.1
    y_pad = max(0.5, (max(ys) - min(ys)) * 0.15)
    y0, y1 = min(ys) - y_pad, max(ys) + y_pad

    def px(x, y):
        return ml + (x - x0) / (x1 - x0) * (W - ml - mr), H - mb - (y - y0) / (y1 - y0) * (H - mt - mb)

    d.rectangle([ml, mt, W - mr, H - mb], outline="black")
    for e in range(int(math.floor(x0)), int(math.ceil(x1)) + 1):
        for m in (1, 2, 5):
            lx = e + math.log10(m)
            if x0 <= lx <= x1:
                gx, _ = px(lx, y0)
                d.line([gx, mt, gx, H - mb], fill=(225, 225, 225))
                d.text((gx - 12, H - mb + 6), f"{m * 10 ** e:g}", fill="black")
    for i in range(6):
        y = y0 + (y1 - y0) * i / 5
        _, gy = px(x0, y)
        d.line([ml, gy, W - mr, gy], fill=(235, 235, 235))
        d.text((8, gy - 6), f"{y:.2f}" if use_psnr else f"1e{y:.1f}", fill="black")
    d.text((W // 2 - 60, H - 25), "ms per frame (log)", fill="black")
    d.text((8, 12), ("PSNR (dB) vs ground truth" if use_psnr else "log10 points per frame") +
           f"   {results['machine'].get('cpus', '?')} CPUs, {results.get('run', '')}", fill="black")
    pts = sorted(zip(xs, ys, rows), key=lambda t: t[0])
    d.line([px(x, y) for x, y, _ in pts], fill=(120, 160, 220), width=2)
    for i, (x, y, r) in enumerate(pts):
        cx, cy = px(x, y)
        d.ellipse([cx - 5, cy - 5, cx + 5, cy + 5], fill=(30, 80, 200))
        cy += 30 if i % 2 else -10  # alternate labels below/above: neighbours on a flat curve do not overlap
        d.text((cx + 8, cy - 16), f"{r['preset']} {r['ms_per_frame']:.0f} ms, x{r['speedup_vs_reference']:.1f}",
               fill="black")
        d.text((cx + 8, cy - 4), f"{r['points_per_frame']:,.0f} pts", fill=(90, 90, 90))
    path = Path(path)
    with atomic_write_path(path, overwrite=overwrite) as tmp:
        img.save(tmp, format="PNG")
    return path
