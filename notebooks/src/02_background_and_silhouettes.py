# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 02 · Background and silhouettes
#
# Carving needs, in every view, the set of pixels where the specimen is: its **silhouette**.  We
# get it by comparing each view with pictures of the empty scene taken from the same place.
#
# **Background model.**  Twenty frames of the empty turntable; their per-pixel median
# $B(x)$ ignores a passing shadow or a flicker that the mean would smear in.
#
# **Difference.**  For colour images, the distance of the RGB vectors,
#
# $$d(x) = \frac{\lVert I(x) - B(x) \rVert_2}{\sqrt{3}},$$
#
# scaled so that a change of $\delta$ grey levels on all three channels gives $d = \delta$.
#
# **Threshold.**  A pixel belongs to the silhouette when $d(x) > \tau$.  The automatic $\tau$ is
# Li's minimum cross-entropy threshold of the difference image, never below five times the
# background frames' noise.  The mask is then cleaned (a small opening and closing, the largest
# components, holes filled), and a **coverage** in $[0, 1]$ along its outline tells how much of
# each border pixel the specimen covers: carving uses it to place the surface between pixels.

# %%
import json
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import organlab as ol
from organlab.silhouette import background_model, difference, silhouette
from organlab.synthetic import AAAPhantom, render_masks
from organlab.widgets import ThresholdPicker

ROOT = next(p for p in [Path.cwd(), *Path.cwd().parents] if (p / "sample_sessions").is_dir())
SAMPLE = ROOT / "sample_sessions" / "aaa_phantom"
session = ol.load_session(SAMPLE)
frames = [session.read(p) for p in session.background_images]
background = background_model(frames)
image = session.read(session.views[0].image)
diff = difference(image, background)

fig, axes = plt.subplots(1, 3, figsize=(14, 3.6))
axes[0].imshow(frames[0]); axes[0].set_title("one empty frame")
axes[1].imshow(image); axes[1].set_title("view 0")
im = axes[2].imshow(diff, cmap="magma"); axes[2].set_title("difference d(x), grey levels")
fig.colorbar(im, ax=axes[2], fraction=0.035)
for ax in axes:
    ax.set_axis_off()
plt.show()

# %% [markdown]
# ## Picking the threshold
#
# The threshold picker shows the silhouette over the view and the histogram of $d$: the
# background is the tall peak near zero (camera noise), the specimen the wide hump to the
# right.  A good threshold lies in the valley between them; the automatic one is dashed.  In
# the widget, move the slider (and the view) and watch the area; the picture below is its
# default state, drawn with a threshold chosen by hand.

# %% tags=["key-picture"]
picker = ThresholdPicker(session, view=0)
print(picker.summary())
picker.threshold = 40.0
print(picker.summary())
picker.figure()

# %%
picker.threshold = None
picker.widget()

# %% [markdown]
# How much does the threshold matter?  From the noise floor up to about 30 grey levels the
# silhouette's area hardly moves: the valley of the histogram is wide, and any threshold in it
# gives the same silhouette.  Above it the threshold eats into the parts of the specimen that
# differ least from what lies behind them (the dark stripes, the legs in front of the grey
# table), and the area falls.

# %%
taus = np.arange(6.0, 101.0, 4.0)
areas = []
for tau in taus:
    picker.threshold = float(tau)
    areas.append(picker.area_px)
picker.threshold = None
plt.figure(figsize=(6, 3.2))
plt.plot(taus, areas, "o-")
plt.axvline(picker.auto_threshold, color="tab:blue", ls="--", label="automatic")
plt.xlabel("threshold (grey levels)")
plt.ylabel("silhouette area (px)")
plt.legend()
plt.show()

# %% [markdown]
# ## Every view
#
# `ol.silhouettes` runs the same steps for all 36 views (the automatic threshold per view).

# %%
sils = ol.silhouettes(session)
fig, axes = plt.subplots(1, 6, figsize=(15, 2.6))
for ax, i in zip(axes, range(0, 36, 6)):
    ax.imshow(sils[i].coverage, cmap="gray")
    ax.set_title(f"view {i}: tau {sils[i].threshold:.1f}", fontsize=9)
    ax.set_axis_off()
plt.show()

# %% [markdown]
# ## Exercises
#
# The sample was rendered, so its exact silhouettes are known: `render_masks(AAAPhantom(), [camera])`
# gives the fraction of each pixel the phantom covers, seen by a camera.  The true camera of view
# `i` is in `truth.json` (below, `true_camera(i)`).
#
# **Exercise 1.**  Compare the automatic silhouette of view 9 (`sils[9].mask`) with the exact one
# (pixels covered at least half): store their intersection over union in `iou_9`.

# %%
truth = json.loads((SAMPLE / "truth.json").read_text())


def true_camera(i):
    """The camera view ``i`` was rendered with (from truth.json)."""
    c, v = truth["camera"], truth["views"][i]
    return ol.Camera(c["K"], c["dist"], v["R"], v["t"], tuple(c["image_size"]))


exact_9 = render_masks(AAAPhantom(), [true_camera(9)], supersample=2)[0] >= 0.5
# BEGIN SOLUTION
iou_9 = np.count_nonzero(sils[9].mask & exact_9) / np.count_nonzero(sils[9].mask | exact_9)
# END SOLUTION
# STUB: iou_9 = None  # your code here

# %%
if iou_9 is None:
    print("Exercise 1: not done yet")
else:
    # measured 0.98: the found outline lies within about a pixel of the true one
    assert 0.95 < iou_9 <= 1.0, iou_9
    print(f"Exercise 1: correct, IoU {iou_9:.4f}")

# %% [markdown]
# **Exercise 2.**  Which threshold gives view 9 the silhouette closest to the truth?  Try
# `silhouette(image_9, background, threshold=t)` for `t` in `candidates`, keep the IoU of each in
# the list `ious` (same order) and the best threshold in `best_t`.  Is it far from the automatic
# one?

# %%
image_9 = session.read(session.views[9].image)
candidates = [8.0, 12.0, 17.0, 25.0, 40.0, 60.0, 90.0]
# BEGIN SOLUTION
ious = []
for t in candidates:
    m = silhouette(image_9, background, threshold=t).mask
    ious.append(np.count_nonzero(m & exact_9) / np.count_nonzero(m | exact_9))
best_t = candidates[int(np.argmax(ious))]
# END SOLUTION
# STUB: ious, best_t = None, None  # your code here

# %%
if best_t is None:
    print("Exercise 2: not done yet")
else:
    assert len(ious) == len(candidates) and best_t in candidates
    check = silhouette(image_9, background, threshold=best_t).mask
    assert abs(ious[candidates.index(best_t)] - np.count_nonzero(check & exact_9) / np.count_nonzero(check | exact_9)) < 1e-12
    assert ious[candidates.index(best_t)] == max(ious) > 0.95
    print(f"Exercise 2: correct, best threshold {best_t:g} (IoU {max(ious):.4f}); automatic {sils[9].threshold:.1f}")
