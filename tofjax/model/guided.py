"""Guided optics: the analytic model with the light's elevation inside the slab (issue 14).

The default optics (:mod:`tofjax.model.components`, seed 000's Eq. 4-5) let all light travel
in the plane at ``c1 = c / n1`` and fall off as ``1/r^2`` round trip. In a slab that guides by
total internal reflection, a ray at elevation ``theta`` (``mu = sin theta``) zig-zags between
the faces and advances in the plane at ``c1 cos theta``; after a diffuse event (a scattering, a
cut edge, skin) light comes back at every elevation the faces guide, ``|mu| < sqrt(1 - 1/n1^2)``.
``ModelOptions(optics="guided")`` models that:

* **time**: a return from in-plane range ``r`` arrives at ``t_e + r (1/c_out + 1/c_j) / c1``,
  ``c_j = cos theta_j`` over a fixed Gauss-Legendre quadrature of the guided band
  (``ModelOptions.elevations`` nodes), ``c_out`` the RMS cosine of the launched beam
  (``|mu| <= sin(fov/2) / n1``, a round beam refracted at the edge);
* **geometry**: the guided return spreads in two dimensions, so it reaches an aperture of
  width ``a`` across the slab's thickness ``h`` with the in-plane angle ``a cos(psi_s) / r``:
  ``1/r`` for backscatter, not ``1/r^2``; the light's share of the emitted fan is
  ``dphi / fov``;
* **amplitudes**, in the Monte Carlo's convention (counts = gain x detected fraction /
  (a h)): the far edge is Lambertian (``R cos(psi_w) c_j / pi`` per steradian), volume
  backscatter has the phase function ``f_back / (2 pi)`` per steradian (``f_back`` =
  ``volume_backscatter_fraction``, the share scattered into the backward hemisphere: 0.5
  for isotropic scattering), attenuation is ``exp(-mu_t r / c)`` along each leg;
* **contacts** with ``ModelOptions(skin=SkinContact())``: a share ``coupling x strength`` of a
  contact disk is in optical contact with skin; each top-face hit under it (``|mu| / (2 h c)``
  per metre of chord) sends ``1 - R_Fresnel(n1 -> n_skin)`` into the skin, which returns its
  diffuse albedo (diffusion theory) as a Lambertian source on the face. The touch amplitude
  and the shadow it casts on the far edge and on the other contacts' returns behind it
  (outbound and, per elevation, on the way back) follow; ``touch_strength`` scales the coupling
  (the Monte Carlo's convention). Without a skin model the guided optics keep the free touch
  strength and shadow opacity, with the guided timing and ``1/D^2`` falloff.

* **second far-edge bounce** (``EDGE_SECOND``): light the lit wall footprint sends diffusely to another
  part of it (across a corner) and that part returns, from the same Lambertian law, no free
  parameter (:func:`_edge_second`).

* **the walls' later bounces** (``EDGE_REVERB``, :func:`_reverb`): a time-resolved radiosity of the walls
  (``REVERB_SEGMENTS_PER_WALL`` segments each, solved per frequency) from the third bounce on, with the beam's
  scattered light; each zone sees it through its rays' wall segments and the volume in front of them. No free
  parameter: against the Monte Carlo in a clear square guide the light after the first return goes from 41% of
  the Monte Carlo's (relative L2 0.51) to 99.1% (0.097).

* **multiple scattering** (``MS_DERIVED``): the phenomenological term's build-up and absorption with the guided
  falloff and timing, and its coupling derived from the geometry (the light scattered twice, out of the fan and
  back into a zone's view; :func:`double_scatter_coupling`); the scene's ``multiple_scattering`` scales it
  relative to its default.

See docs/tradeoff.md for the comparison with the Monte Carlo.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..scene import Scene, Waveguide
from .components import SPEED_OF_LIGHT_M_PER_S, Nodes, deposit, smooth_like_deposit

__all__ = ["GuidedGeometry", "guided_node_masses", "hg_backward_fraction", "inward_normals", "launch_band"]

#: The distributed terms (volume, multiple scattering) use ``elevations // DIST_DIVISOR`` nodes:
#: they are smooth in time already, and their cost grows with the node count.
DIST_DIVISOR = 8
#: Near field of the distributed terms without :data:`NEAR_FIELD_APERTURE`: ``1/r`` becomes ``1/sqrt(r^2 + r0^2)``
#: with ``r0`` this share of the thickness. 0.3 was fitted to the Monte Carlo on optoskin (relative L2 0.110 at 0.3,
#: 0.127 at 0.2, 0.140 at 0.6: experiments/study_mc_guided.py). With the aperture's near field it only shapes the
#: far field's ``1/r`` of the rays that have ended (far from the sensor, where it is ``1/r`` to 1e-4).
NEAR_FIELD_PER_THICKNESS = 0.3
#: The distributed terms' near field from the aperture's geometry (:func:`_near_field_table`) instead of
#: :data:`NEAR_FIELD_PER_THICKNESS`. A zone is a condition on the angle of arrival (as in the Monte Carlo's
#: next-event estimation), and light from a point at range ``r`` reaches the aperture (``a`` wide along the edge)
#: over arrival angles ``a cos(psi) / r`` wide: near the sensor a point's light spreads over the neighbouring zones,
#: and at the fan's two ends out of it. In the Monte Carlo the two outer zones of each sensor see 0.60-0.96 of the
#: middle zone's light in the first 4 bins after the emission, where the thickness-based near field saw every zone
#: alike (0.64-1.31, the rays' projection on the edge alone; with the aperture's 0.59-0.98). Every ray's share of
#: every zone, integrated from the sensor out with the exact arrival angles, is tabulated when the model is built and
#: differenced over each time node; far from the sensor it is the ray's own zone's ``a cos(psi) / r``, as before.
#: No free parameter (the aperture is ``ModelOptions.aperture_m``, as the Monte Carlo's ``MCOptions.aperture_m``).
#: It costs 1.08-1.20x of the guided model's forward time (docs/tradeoff.md, "The near field from the aperture").
NEAR_FIELD_APERTURE = True
#: The far edge's first return spread over the zones by the same arrival angles (:func:`_edge_mixing`): a wall point
#: at ``L`` reaches the aperture over ``ray +- (a/2) cos(psi) / L``, so a ray within that of a zone's limit gives
#: part of its return to the neighbouring zone (or, at the fan's two ends, to none): 2-5% of the rays next to a
#: limit at 10-30 cm. Each zone takes its own rays and the ``EDGE_APERTURE_RAYS`` nearest of each neighbour (a
#: ray further in spills nothing wherever ``L > 2.8 cm``, at 8 rays per zone on a 29 degree fan).
EDGE_APERTURE = True
EDGE_APERTURE_RAYS = 2
#: The aperture's near-field table (:func:`_near_field_table`): ranges from NF_R_MIN to NF_R_MAX (m), NF_POINTS
#: points uniform in log r. Below NF_R_MIN every ray's arrival angles cover the whole fan (its light is linear in r);
#: beyond NF_R_MAX the table's last value holds (the spill is then below 1e-6 of the far field's).
NF_R_MIN, NF_R_MAX, NF_POINTS = 1e-5, 4.0, 512
#: Each ray stands for an interval of angles (``dphi``): the aperture's spread is averaged over this many angles
#: across it (a ray at the interval's centre alone would spill nothing until the spread reaches the zone's limit).
NF_SUBRAYS = 16
#: Add the second-order touch term (:func:`_touch_diffuse`: far-edge light frustrated at the contacts).
#: Off: against the Monte Carlo it moves the touch scene's error only from 0.140 to 0.138 and costs
#: 2.4x the default optics on the touch scene instead of 1.5x (docs/tradeoff.md).
SECOND_ORDER = False
#: With ``SECOND_ORDER``: also the reversed order of the same paths (sensor -> contact -> skin return
#: -> diffuse wall -> sensor), each with its forward twin's amplitude and delay (reciprocity),
#: detected in the wall point's zone. Off: against the Monte Carlo one contact's signal fits worse
#: with it near walls and corners (relative L2 0.46 against 0.24 at 2 cm from a corner, first order
#: alone; experiments/mc_contact_walls.py, docs/results/mc_contact_walls.json).
SECOND_ORDER_RECIPROCAL = False
#: Add the far edge's second diffuse bounce (:func:`_edge_second`: light the lit wall footprint sends to
#: another part of it, e.g. across a corner, and that part returns). ``EDGE_SECOND_STRIDE`` (with
#: :data:`EDGE_SECOND_GROUPS` off): one ray in every this many of a zone is a source (the middle one; its power times
#: the stride). 8: one per zone at the default 8 rays per zone.
EDGE_SECOND = True
EDGE_SECOND_STRIDE = 8
#: The second bounce's sources: one per zone and wall it sees, at its rays' power-weighted centre and with their
#: power (:func:`_wall_groups`), instead of ``EDGE_SECOND_STRIDE``'s middle rays. A zone whose footprint spans a corner
#: then lights each wall's part from the other's; with its middle ray alone, the part on the middle ray's own wall
#: received nothing. On OptoSkin the zones that see a corner carried the far edge's worst misfit. Against the Monte
#: Carlo baseline: reduced chi-square 64x 2.920 -> 2.686, 16x 1.472 -> 1.409; the fit's mu_s + mu_a error +3.8% ->
#: +4.9% (+3.7% -> +4.8%); every ray a source (stride 1) gives 2.691 at 1.75x the guided model's time, this 1.01-1.06x
#: (experiments/near_field_aperture.py --study edge_groups, docs/results/edge_groups.json).
EDGE_SECOND_GROUPS = True
#: The second bounce's return leg spread in time as the first bounce's: its return elevations cut into this many
#: groups of neighbours, each at its own amplitude-weighted delay (0: all at the band's mean ``1 / cos``). 5 (3 before
#: the nineteenth session): the 64x calibration of the Monte Carlo baseline's reduced chi-square 3.95 -> 3.48 with
#: :data:`EDGE_SCATTER` (7 groups: 3.41), 16x 1.72 -> 1.61 (experiments/near_field_aperture.py --study edge_scatter).
#: At the twenty-fifth session's model, 7 groups: 64x on 256 Monte Carlo runs 2.216 -> 2.146 (11 groups: the same) at
#: 1.07x the guided model's time (docs/tradeoff.md "The deconvolution that keeps its light"); with term 1's return-leg
#: fix (twenty-sixth) 2.168 -> 2.097 (docs/tradeoff.md "Term 1's return leg against the direct return's"). 8 (every
#: return elevation its own group at the default 8 elevations) since the twenty-seventh session: with
#: :data:`SCATTER_FLUENCE` and :data:`SCATTER_SECOND`, 64x 2.305 -> 2.233 (64 runs), 2.117 -> 2.042 (256; 7 groups the
#: same to 4 digits), at 1.008x the guided model's time on the bench's touch scene
#: (experiments/bench_guided_switch.py --switch EDGE_SECOND_SPREAD --values 5,8).
EDGE_SECOND_SPREAD = 8
#: Contacts frustrate the second bounce's wall-to-wall legs too (:func:`_leg_transmission`), not only
#: its first leg and its return (a contact in a corner sits on the legs across it). Off: against the
#: Monte Carlo it brings one contact's signal 2 cm from a corner closer (relative L2 0.235 -> 0.188,
#: experiments/mc_contact_walls.py) but six-contact detection at 64x exposure no better (precision /
#: recall 88.7 / 93.1% against 88.3 / 94.4% on the same data, experiments/eval_mc_data.py), and it
#: costs the guided model 1.45x on touch-six and the detection 1.55x.
EDGE_SECOND_SHADOW = False
#: The second bounce's exchange from a source to a receiving wall segment, exact in the plane: with
#: :data:`EDGE_SECOND_GROUPS` each source is its group's stretch of wall, lit evenly, and Hottel's crossed strings give
#: the share of its in-plane diffuse emission each ray's segment receives (a table built once, :func:`_wall_group_views`);
#: without, each source is a point and the share is its ``cos(psi) / 2`` per radian integrated over the angle the
#: segment subtends, ``|sin(psi_2) - sin(psi_1)| / 2``. The delay and attenuation take the in-plane distance from the
#: source's centre. Off: the segment's centre alone, ``cos_i cos_j len / (2 r)`` with ``r^2 = d^2 + thickness^2``,
#: whose thickness term (5 mm on OptoSkin) took 36-84% of the exchange across a corner, where a zone's two walls'
#: stretches are a few mm apart. Against the Monte Carlo baseline at 64x: reduced chi-square 2.233 -> 2.117 (64 runs),
#: 2.042 -> 1.939 (256), 1.980 -> 1.877 (1024); at the true optics the corner zones' two-bounce excess 0.66-0.68 ->
#: 0.25 thousandths of the wall light; 0.95x the guided model's time (twenty-ninth session, docs/tradeoff.md "The
#: second bounce's exchange, exact in the plane").
EDGE_SECOND_EXACT_VIEW = True
#: Add the walls' later diffuse bounces (:func:`_reverb`): a time-resolved radiosity of the walls from the third
#: bounce on (the first two are :func:`_edge` and :func:`_edge_second`), with the beam's scattered light, seen by
#: each zone through its rays' wall segments and the volume in front of them. Against the Monte Carlo in a clear
#: square guide the light after the first return goes from 41% of the Monte Carlo's to 99.1% (tests/test_guided.py);
#: on OptoSkin the Monte Carlo's light where the model had none from 2.0-2.4% to 0.1%
#: (experiments/mc_baseline_time_ratio.py). With it the guided model costs 1.84x / 1.97x the default optics' on the
#: bench's baseline / touch scene (1.3x without it; 3.5-3.8x with the term's first form, which summed 64 orders by
#: doubling and took each delay's phases by complex exponentials; `tofjax bench tradeoff`, docs/tradeoff.md).
EDGE_REVERB = True
#: The radiosity's wall segments per wall (6 since the twenty-third session, 4 before: at the scene's optics 4 gives
#: the same light as 8 and 16 within 0.002 relative L2, but a 64x calibration of the Monte Carlo baseline sees the
#: difference: reduced chi-square 2.686 / 2.565 / 2.465 / 2.432 / 2.402 at 4 / 5 / 6 / 7 / 8 segments per wall, which
#: cost 1 / 1.05 / 1.09 / - / 1.33x the guided model's time; experiments/near_field_aperture.py --study
#: reverb_segments, docs/results/reverb_segments.json; :data:`REVERB_STRINGS` for the same at its session), the most
#: time nodes it is solved on (a coarser grid than the model's where that has more: the
#: field is smooth in time: on OptoSkin's baseline the model at 64 and 128 nodes agrees within 5e-4 of its peak, the
#: field itself within 0.099 / 0.029 relative L2 of its 256-node form with :data:`REVERB_SPREAD`, 0.225 / 0.090 without,
#: its light within 0.02% and its mean delay within 0.006 bins at 64 nodes (both converge at second order since the
#: volume view's first node and the box back onto the model's nodes were mended, see :func:`_reverb`: before, 64 nodes
#: had 1.4% more light than 256, 0.51 bins early); experiments/reverb_spread_grid.py,
#: docs/results/reverb_spread_grid_second_order.json), and how its orders after the
#: fifth bounce are summed:
#: 0, a geometric train (:func:`_geometric_tail`); N, N more orders one by one (a reference for the tests).
REVERB_SEGMENTS_PER_WALL = 6
REVERB_NODES = 64
REVERB_EXACT_ORDERS = 0
#: The field's exchange between two segments by Hottel's crossed strings (exact for straight segments of the guide's
#: convex outline, finite where two meet at a corner) instead of the centres' ``cos_k cos_l len_l / (2 r)``, which
#: sent out 1-5% more light than a segment reflects. The 64x calibration of the Monte Carlo baseline's reduced
#: chi-square 3.48 -> 3.30, 16x 1.61 -> 1.56, at no cost per call (experiments/near_field_aperture.py --study
#: reverb_strings). With it, 5 / 6 / 8 segments per wall give 3.20 / 3.11 / 3.07 at 1.10 / 1.07 / 1.28x the guided
#: model's time (docs/tradeoff.md "The field's exchange between wall segments by crossed strings").
REVERB_STRINGS = True
#: The radiosity's period over the histogram's window: the field is solved on a periodic grid this many windows
#: long, so light still in the guide a period after it arrived wraps onto the window's start. 1.5 (was 2): on
#: OptoSkin's baseline the field moves from its 8-window form by 7e-5 relative L2 at the fitted end reflectance 0.5
#: (2: 2e-5), 1.7% at 0.9 and 5.4% at 1 (2: 0.25% and 1.3%; of the far edge's whole term 0.19% and 0.77%), for
#: 0.86x / 0.87x the guided model's time on the baseline / touch scene (96 nodes and 49 frequencies for 128 and 65;
#: experiments/bench_guided_switch.py --switch REVERB_PADDING, docs/results/bench_guided_switch_reverb_padding*.json).
REVERB_PADDING = 1.5
#: The field's volume view (:func:`_reverb_volume`) from the walls' irradiance a mean forward distance ahead
#: (:func:`mean_forward_distance` at the band's mean in-plane speed): the light inside a diffuse field reaches
#: the walls that much later than it is there. On OptoSkin's Monte Carlo baseline the light after bin 60 comes
#: to relative L2 0.133 from 0.173 (Monte Carlo over model 0.91-1.00 from 0.83-0.92).
REVERB_VOLUME_LEAD = True
#: Contacts frustrate the field's wall-to-wall legs too (:func:`_field_leg_transmission`). Off: near a corner it
#: brings one contact's removed light to the Monte Carlo's (40-54 -> 70-81 counts against 65-75, relative L2 0.23
#: -> 0.195 at 2 cm; experiments/mc_contact_walls.py) but six-contact detection at 64x no better (pooled precision /
#: recall 91.9 / 90.3% against 92.3 / 92.0%; experiments/eval_mc_data.py --guided-switch REVERB_LEGS=true).
REVERB_LEGS = False
#: The field's delays spread as its elevations do: a wall-to-wall leg ``r`` long takes ``r / (c1 cos)`` at each
#: guided elevation (a diffuse wall draws a new one for each leg), a ray's view of its wall segment each return
#: elevation's ``L / (c1 cos)``; with it each leg's and each view's transform carries the Gaussian of that spread
#: (its variance from the band's weights) on top of its mean delay. Without it the grid's own blur (the deposit's
#: spline at ``REVERB_NODES``) was the only spread, and the 64x calibration of the Monte Carlo baseline moved with the
#: grid: reduced chi-square 6.50 / 5.79 / 7.89 and mu_s + mu_a +17 / +6 / -13% at 32 / 64 / 128 nodes; with it 5.50 /
#: 5.54 and +10 / +6% at 64 / 128 (experiments/reverb_spread_grid.py --calibrate). With the grid's first-order errors
#: mended (:data:`REVERB_NODES`): 5.59 / 5.68 and +8 / +4% with it, 6.50 / 5.94 / 8.05 and +14 / +2 / -15% without.
REVERB_SPREAD = True
#: With :data:`REVERB_SPREAD`, the field's grid takes its own spread back out of those Gaussians: each delay laid on
#: the coarse grid (:func:`_shifts`: a quadratic B-spline, variance a quarter of a node squared, whatever the delay)
#: and the box back onto the model's nodes (:func:`_reverb`) spread the field by the grid's spacing, not by the light's
#: physics. Each leg's Gaussian takes a spline's variance less and each view's two (its own and the light's
#: arrival's), **each only down to zero**: a leg or view sharper than the grid keeps its spline, so no term is ever
#: sharpened below its own delay and the field does not ring. The volume view's arrival and lead, and the box (less
#: the one fine spline every other term's deposit has), come off the whole field before it goes back in time (a
#: Gaussian of negative variance: the splines' transforms fall faster at high frequencies than it rises). On
#: OptoSkin's baseline the far edge's term at 64 nodes moves from its 256-node form by relative L2 0.00083 instead of
#: 0.0023 (128 nodes without it: 0.00062), for the same time side by side (0.99x); the 64x calibration of the Monte
#: Carlo baseline's reduced chi-square 2.465 -> 2.410 (64 runs), 2.281 -> 2.216 (256 runs), 16x 1.354 -> 1.331 /
#: 1.335 -> 1.312 (docs/tradeoff.md "The deconvolution that keeps its light"). The first form (twenty-fourth session)
#: let a leg's or view's variance go negative: where the field is sharp on its grid it rang, and the clip at 0 turned
#: the negative lobes into light (up to 51% in the last lit bins of test_guided_edge_attenuates_in_time_like_beer_lambert,
#: 13% allowed; this form: 11.5%, 12.4% without the switch).
REVERB_DECONVOLVE = True
#: The beam's light scattered into the guided band meets the walls where the geometry sends it (each wall segment's
#: share of every point along each ray's in-plane isotropic light, ``SCATTER_SHARE_POINTS`` points per ray) and at
#: its mean first-hit delay per segment, instead of evenly along the perimeter when the beam reaches its wall
#: (:func:`_reverb`, :func:`_first_hit_shares`): most of it lands on the walls beside and ahead of the fan, near the
#: walls the zones see, and some of it before the beam reaches its own wall. Against the Monte Carlo baseline:
#: reduced chi-square 64x 3.268 -> 2.955, 16x 1.555 -> 1.480, the fit's mu_s + mu_a error +5.6% -> +2.5% (+5.4% ->
#: +3.7%), 1.01x the guided model's time (experiments/near_field_aperture.py --study scatter_share,
#: docs/results/scatter_share.json).
REVERB_SCATTER_SHARE = True
SCATTER_SHARE_POINTS = 16
#: Discrete top-face hits under a contact (:func:`_frustrated`). Off: the continuous form, which the
#: Monte Carlo's next-event estimation uses too (so the benchmark cannot tell them apart); the analog
#: Monte Carlo (discrete hits) shadows less (docs/tradeoff.md).
DISCRETE_HITS = False
#: A contact's return crosses the other contacts between it and the sensor (:func:`_contacts_between`), out and
#: back, over ``CONTACT_LINES`` lines across its disk. Off: every contact returns as if alone.
CONTACT_SHADOW = True
CONTACT_LINES = 5


#: Add the light the walls and the volume exchange around each zone's lit wall (:func:`_edge_scatter`): the beam's light
#: scattered on its way out on to the lit walls (returned like the beam's own light there), and the lit walls'
#: diffuse light scattered back to the sensor by the volume in front of them (which reaches a zone before its own
#: first return where a neighbour's wall is nearer). Each is a kernel of path differences from the zone's first
#: return, tabulated from the geometry (:func:`_scatter_tables`: ``SCATTER_BINS`` bins ``SCATTER_BIN_M`` wide from
#: ``SCATTER_MIN_M``, ``SCATTER_SOURCES`` points along each ray, ``SCATTER_ELEMENTS`` elements per ray's footprint);
#: the reverberant field (:func:`_reverb`) takes the beam's scattered light from its second wall hit on. Against the
#: Monte Carlo baseline at 64x: reduced chi-square 4.36 -> 3.48, the volume window's excess 5,593 -> 2,741
#: (experiments/near_field_aperture.py --study edge_scatter, docs/results/edge_scatter.json); 1.12x the guided
#: model's time (experiments/bench_guided_switch.py).
EDGE_SCATTER = True
SCATTER_BINS = 72
SCATTER_BIN_M = 0.01
SCATTER_MIN_M = -0.2
SCATTER_SOURCES = 32
SCATTER_ELEMENTS = 2
#: The largest n1 the kernels' time window is sized for (light beyond it is cut).
SCATTER_MAX_N1 = 2.5
#: A third kernel (:func:`_scatter_tables`' term 2): the lit walls' diffuse light scattered once by the volume on to
#: the walls in view, which return it as their first bounce (light of two bounces and one scattering, ``R^2 mu_s``:
#: :func:`_edge_second` sees the second bounce's direct light only, the field's legs move scattered light on to where
#: they were going, and the field is seen from the third bounce on). The scattering points on a grid of
#: ``SCATTER_GRID_M`` (1 cm: 3.3% from 5 mm in a 20 cm guide, 2 cm 9%). **Off**: against the Monte Carlo baseline
#: (before :data:`REVERB_SCATTER_SHARE`) it takes the 64x chi-square only from 3.268 to 3.245 (16x 1.555 -> 1.551)
#: and moves the fit's mu_s + mu_a error from +5.6% to +8.1% (+5.4% -> +8.0%); with REVERB_SCATTER_SHARE 2.955 ->
#: 2.933 and +2.5% -> +5.0% (one calibration, scratch). The Monte Carlo's two-bounce scattered light comes sooner than
#: this term brings it, and is spent by 14 bins after each far edge's peak, where the term still adds
#: (experiments/near_field_aperture.py --study scatter_redirect, docs/results/scatter_redirect.json;
#: experiments/wall_light_orders.py).
SCATTER_REDIRECT = False
SCATTER_GRID_M = 0.01
#: The kernels are applied to a zone's whole first return, which is weighted to the zone's near rays (a wall returns
#: ``1 / L`` of what reaches it), while the light they carry is weighted to its far rays (more wall, more volume). On,
#: each table entry's delay is taken from the return of its own ray or element, less the zone's mean return (weighted
#: as the first return is), and the beam's scattered light on a wall element is returned with that element's own
#: ``cos cos / L``, not the zone's mean. A 60-degree zone's kernel light then agrees with the sum of the same view cut
#: into 16 narrow zones within 0.4% in amount and 0.2 of a bin in mean delay (3.5% and 0.9 of a bin early before;
#: tests/test_edge_scatter.py). Against the Monte Carlo baseline: reduced chi-square 64x 2.955 -> 2.920, 16x 1.480 ->
#: 1.472; the fit's mu_s + mu_a error +2.5% -> +3.8% (+3.7% -> +3.7%); 1.006x the guided model's time
#: (experiments/near_field_aperture.py --study own_return, docs/results/own_return.json).
SCATTER_OWN_RETURN = True
#: The diffuse legs' own spread in time: light scattered into the guided band travels its in-plane length ``rho`` at
#: ``1 / cos`` of its elevation, from 1 to ``n1`` (1.4 at n1 = 1.4), not at the band's mean alone. With ``n > 0``
#: each table entry is binned at ``n`` Gauss-Legendre elevations of its diffuse leg (uniform in ``mu``, the guided
#: share of isotropic light), each with its own length ``rho / cos`` (the bins' mean lengths carry it, so the fitted
#: n1 still sets each bin's delay and attenuation); 0: every entry at the band's mean ``1 / cos``. Build time only.
#: **Off**: against the Monte Carlo baseline at 64x (256 runs) 4 nodes take the reduced chi-square from 2.168 to
#: 2.196 and the fit's mu_s + mu_a error from +4.2% to +5.9%; at the true optics the kernels' light moves earlier, to
#: the bins before each far-edge peak where the model is already too bright (twenty-seventh session,
#: docs/tradeoff.md "The kernels' legs as the volume receives them").
SCATTER_SPREAD = 0
#: Term 1's kernel (the lit walls' light scattered back by the volume) applied to the far edge's second bounce too
#: (:func:`_edge_second`'s return): the footprint's walls, lit a second time by the first bounce's diffuse light,
#: re-emit it into the same volume in front of them, which scatters it back as it does the first bounce's (light of
#: two bounces and one scattering, ``R^2 mu_s``, which the field's volume view counts from the third bounce on only).
#: Against the Monte Carlo baseline at 64x: reduced chi-square 2.358 -> 2.322 (64 runs), 2.168 -> 2.133 (256); at
#: the true optics the Monte Carlo's excess of ``R^2 mu_s`` light falls from 7.18 to 6.32 thousandths of the wall
#: light, evenly over the bins after each peak (experiments/wall_light_orders.py); 1.02x the guided model's time.
SCATTER_SECOND = True
#: The volume's legs weighted as a volume point receives light: the fluence a Lambertian wall gives a point is uniform
#: in ``mu`` (constant radiance over the mirror images' strip, whose solid angle is ``dphi dmu``), so term 1's wall-to-
#: volume leg (and term 2's) travels at the isotropic band's mean ``1 / cos`` (``g_iso``, 1.108 at n1 = 1.4), not at
#: the flux-weighted ``g_wall`` (1.098) of what a sensor's aperture receives from a wall. Off: ``g_wall``. Against the
#: Monte Carlo baseline at 64x: 2.358 -> 2.342 (64 runs), 2.168 -> 2.153 (256), mu_s + mu_a +4.2% -> +4.0%; with
#: :data:`SCATTER_SECOND` 2.305 / 2.117 (twenty-seventh session).
SCATTER_FLUENCE = True
#: Multiple scattering's coupling derived from the geometry (:func:`double_scatter_coupling`): the light scattered
#: twice, once out of the beam and once back into a zone's view, over what the zone's single backscatter brings,
#: per unit of ``mu_s`` times the path, is ``arccos(1/n1)`` (the guided share of isotropic scattering, with its
#: longer path across the slab) times a zone's in-plane view of the beam, about 0.17-0.19 on OptoSkin's zones. The
#: scene's ``multiple_scattering`` scales it relative to its default (:data:`MS_REFERENCE`: the default is the
#: derived value, 0 none). Off: the coupling is ``multiple_scattering`` itself (0.5 by default), 2.1-2.7x what the
#: Monte Carlo with absorbing edges shows (1.06-1.3x the derived one), which a 64x fit of the Monte Carlo baseline
#: took out by raising mu_s + mu_a 15% (5.6% with it; experiments/near_field_aperture.py --study ms_derived,
#: docs/tradeoff.md "Multiple scattering's coupling from the geometry").
MS_DERIVED = True
#: The scene's default ``multiple_scattering``: with :data:`MS_DERIVED` the guided optics read the scene's value
#: relative to it (the default means the derived coupling). Read at trace, so it keys the program as the switches do.
MS_REFERENCE: float = next(f.default for f in dataclasses.fields(Waveguide) if f.name == "multiple_scattering")


#: The names of the switches above, in order (every upper-case bool, int or float of this module): tracing reads
#: them, so :func:`tofjax.model.forward._trace_switches` keys every compiled program by their values.
SWITCH_NAMES = tuple(k for k, v in globals().items() if k.isupper() and isinstance(v, (bool, int, float)))


def hg_backward_fraction(g: float) -> float:
    """Share of Henyey-Greenstein scattering into the backward hemisphere (0.5 for g = 0): the
    ``volume_backscatter_fraction`` that matches a Monte Carlo with anisotropy ``g``."""
    if abs(g) < 1e-9:
        return 0.5
    return (1.0 - g) / (2.0 * g) * ((1.0 + g) / math.sqrt(1.0 + g * g) - 1.0)


def _double_scatter_kernel(delta):
    """``K(delta)``: the in-plane double-scattering integral between two rays ``delta`` apart (radians).

    With the sensor at the origin, a first scattering at range ``x1`` on one ray and a second at ``x2`` on the
    other, both scattering isotropically in the plane and the light spreading as ``1/rho`` between them, the
    light that comes back after a total path ``x1 + rho + x2 = 1`` is ``int int dx1 dx2 delta(1 - L) / rho``.
    Solving ``L = 1`` for ``x2`` (only ``x1 < 1/2`` has a root) and dividing by ``dL/dx2`` leaves
    ``int_0^(1/2) dx1 / (1 - x1 (1 + cos delta))`` = ``ln(2 / (1 - cos delta)) / (1 + cos delta)``: scale-free
    (the same at every path), ``ln(2 / |delta|)`` as ``delta -> 0`` (integrable).
    """
    c = np.cos(delta)
    return np.log(2.0 / np.maximum(1.0 - c, 1e-300)) / (1.0 + c)


def _double_scatter_interval(a, b, n: int = 8):
    """``int_a^b K(delta) d delta`` (arrays of bounds): the logarithm ``ln(2 / |delta|)`` exactly, the smooth rest
    (``K - ln(2 / |delta|)``, 0 at 0) by ``n``-point Gauss-Legendre."""
    a, b = np.asarray(a, float), np.asarray(b, float)

    def F(d):  # an antiderivative of ln(2 / |d|), odd
        ad = np.abs(d)
        return np.sign(d) * ad * (math.log(2.0) + 1.0 - np.log(np.where(ad > 0, ad, 1.0)))

    x, w = np.polynomial.legendre.leggauss(n)
    mid, half = 0.5 * (a + b), 0.5 * (b - a)
    d = mid[..., None] + half[..., None] * x
    ad = np.abs(d)
    rest = np.where(ad > 1e-6, _double_scatter_kernel(d) - np.log(2.0 / np.where(ad > 0, ad, 1.0)), 0.0)
    return F(b) - F(a) + half * np.sum(w * rest, axis=-1)


def double_scatter_coupling(ray_angle, ray_width, live) -> np.ndarray:
    """Each zone's in-plane double-scattering coupling ``C_2D`` (NumPy, at build; (S, Z)).

    Light scattered twice, first anywhere in the emitted fan and then back into a zone's view, against the zone's
    single backscatter, is ``mu_s L C`` at total path ``L`` (small ``mu_s L``; :func:`_double_scatter_kernel`):
    ``C_2D = (1 / 2 pi) int_fan K(phi' - phi) d phi'`` per ray ``phi`` of the zone, the fan's rays weighted as the
    model emits them (uniform in angle; a ray that leaves the guide at once, ``live`` False, sends nothing), then
    averaged over the zone's live rays. In the slab the middle leg keeps the guided share of isotropic scattering,
    ``sin theta_c``, with a fluence ``1 / cos theta`` for its slant path: ``theta_c = arccos(1 / n1)`` in all, which
    the model applies per call (n1 is fitted). The slant path's later arrival moves ``C`` by 2% (Monte Carlo
    integration), not modelled. Infinite medium: a ray's wall ends the light it carries elsewhere in the model.

    ``ray_angle`` (S, Z, A) radians, ``ray_width`` (Z,) each ray's angle, ``live`` (S, Z, A) bool.
    """
    ang = np.asarray(ray_angle, float)
    S, Z, A = ang.shape
    width = np.broadcast_to(np.asarray(ray_width, float)[None, :, None], ang.shape)
    live = np.asarray(live, bool)
    out = np.zeros((S, Z))
    for s in range(S):
        phi, w, on = ang[s].reshape(-1), width[s].reshape(-1), live[s].reshape(-1)
        # (targets, sources): the integral of K over each source ray's interval, relative to the target ray
        lo = (phi - 0.5 * w)[None, :] - phi[:, None]
        hi = (phi + 0.5 * w)[None, :] - phi[:, None]
        per_ray = (np.sum(np.where(on[None, :], _double_scatter_interval(lo, hi), 0.0), axis=1) / (2.0 * math.pi)).reshape(Z, A)
        n_live = live[s].sum(axis=1)
        out[s] = np.where(n_live > 0, np.sum(np.where(live[s], per_ray, 0.0), axis=1) / np.maximum(n_live, 1), 0.0)
    return out


def _fresnel(n_in, n_out, cos_i):
    """Unpolarised Fresnel reflectance from ``n_in`` into ``n_out`` (1 beyond the critical angle)."""
    cos_i = jnp.clip(cos_i, 1e-9, 1.0)
    sin_t2 = (n_in / n_out) ** 2 * (1.0 - cos_i**2)
    tir = sin_t2 >= 1.0
    cos_t = jnp.sqrt(jnp.clip(1.0 - sin_t2, 1e-18, 1.0))
    rs = ((n_in * cos_i - n_out * cos_t) / (n_in * cos_i + n_out * cos_t)) ** 2
    rp = ((n_in * cos_t - n_out * cos_i) / (n_in * cos_t + n_out * cos_i)) ** 2
    return jnp.where(tir, 1.0, 0.5 * (rs + rp))


class GuidedGeometry(eqx.Module):
    """Per-ray factors of the guided optics, fixed by the scene (hardware), built with the model."""

    cos_sensor: jax.Array  # (S, Z, A) ray direction against the sensor edge's inward normal
    cos_wall: jax.Array  # (S, Z, A) return direction against the far wall's inward normal
    sensor_normal: jax.Array  # (S, 2) inward normal of each sensor's edge
    wall_normal: jax.Array  # (S, Z, A, 2) inward normal of the wall each ray ends on
    dphi: jax.Array  # (Z,) in-plane angle each ray stands for
    x: jax.Array  # (J,) Gauss-Legendre nodes on [0, 1] (mu / mu_guided)
    wx: jax.Array  # (J,) their weights
    xd: jax.Array  # (Jd,) fewer nodes for the distributed terms (smooth in time already)
    wxd: jax.Array
    fov: float = eqx.field(static=True)
    thickness_m: float = eqx.field(static=True)
    aperture_m: float = eqx.field(static=True)
    skin: object = eqx.field(static=True)  # SkinContact or None
    perimeter_m: float = eqx.field(static=True, default=0.0)  # the walls' length
    forward_m: float = eqx.field(static=True, default=0.0)  # mean distance to a wall, random point and direction
    seg_len: jax.Array = None  # (M,) wall segments of the reverberant field (:func:`_reverb`): their lengths
    seg_r: jax.Array = None  # (M, M) centre-to-centre distances (the thickness added in quadrature)
    seg_view: jax.Array = None  # (M, M) share of segment k's in-plane diffuse emission that segment l receives
    ray_seg: jax.Array = None  # (S, Z, A) the segment each ray's far wall point lies in
    seg_xy: jax.Array = None  # (M, 2) segment centres
    seg_tan: jax.Array = None  # (M, 2) unit vectors along each segment
    nf_w: jax.Array = None  # (S, Z) the aperture's near field (:func:`_near_field_table`): the far field's 1/r weight
    nf_tab: jax.Array = None  # (N - 1, S, Z, 2) its integral from 0 less the far field's (value, slope per interval)
    nf_phi0: jax.Array = None  # (S, Z) its integral from 0 to the grid's first range
    edge_mix: jax.Array = None  # (S, Z, A, Z * A) the far edge's first returns shared among the zones (_edge_mixing)
    sc_w: jax.Array = None  # (S, Z, T, SCATTER_BINS) :func:`_edge_scatter`'s T kernels (:func:`_scatter_tables`): weights
    sc_a: jax.Array = None  # their bins' mean lengths: the beam's leg less the direct one's
    sc_b: jax.Array = None  # the diffuse leg
    sc_c: jax.Array = None  # the view's leg less the direct return's
    ms_c2d: jax.Array = None  # (S, Z) multiple scattering's in-plane coupling (:func:`double_scatter_coupling`)
    hs_share: jax.Array = None  # (S, Z, A, M) each wall segment's share of each ray's scattered light (_first_hit_shares)
    hs_x: jax.Array = None  # (S, M) its mean range along the rays where it scattered
    hs_r: jax.Array = None  # (S, M) and its mean in-plane distance from there to the segment
    es_groups: jax.Array = None  # (S, I, Z, A) the second bounce's sources: each zone's rays by the wall they end on
    es_normal: jax.Array = None  # (S, I, 2) and that wall's inward normal
    es_view: jax.Array = None  # (S, Z, A, I) the share of each group's diffuse in-plane emission each ray's segment gets
    sc_terms: tuple = eqx.field(static=True, default=())  # the kernels' names, in order (:func:`_scatter_terms`)
    sc_off: int = eqx.field(static=True, default=0)  # the kernels' time nodes before the first return's
    sc_nodes: int = eqx.field(static=True, default=0)  # and in all

    @classmethod
    def from_scene(cls, scene: Scene, ray_angle: np.ndarray, zone_lo, zone_hi, elevations: int, aperture_m: float,
                   skin, dtype, node_width_s: float | None = None) -> "GuidedGeometry":
        """``node_width_s``: the model's time step (sizes :func:`_edge_scatter`'s kernels; default: a tenth of a bin)."""
        if getattr(scene, "waveguide", None) is None:
            from ..config import ConfigError

            raise ConfigError("optics: 'guided' needs a waveguide (a free-space scene has no slab to guide light)")
        lx, ly = scene.waveguide.size_m
        ang = np.asarray(ray_angle, float)  # (S, Z, A)
        S, Z, A = ang.shape
        c, s = np.cos(ang), np.sin(ang)
        normals = inward_normals(scene)  # (S, 2)
        cos_sensor = np.clip(c * normals[:, None, None, 0] + s * normals[:, None, None, 1], 0.0, 1.0)
        # which wall each ray ends on: the nearer of the x and y walls along it
        xy = np.array([sp.position_m for sp in scene.sensors], float)[:, None, None, :]
        tx, ty = _to_walls(lx, ly, xy[..., 0], xy[..., 1], c, s)
        cos_wall, wall_normal = _wall_hit(tx, ty, c, s)
        width = np.asarray(zone_hi, float) - np.asarray(zone_lo, float)
        rel = ang[0] - math.radians(scene.sensors[0].direction_deg)  # (Z, A): the same for every sensor
        ray_length = np.clip(np.minimum(tx, ty), 0.0, None)  # (S, Z, A): 0 for a ray that leaves the guide at once
        normal_angle = np.arctan2(normals[:, 1], normals[:, 0])[:, None, None]
        psi = np.mod(ang - normal_angle + math.pi, 2.0 * math.pi) - math.pi  # (S, Z, A) from the edge's normal
        w_ray = (width / A / (math.radians(scene.sensor.fov_deg) * float(scene.waveguide.thickness_m)))[None, :, None]
        w_ray = np.where(ray_length > 0, w_ray, 0.0)  # (S, Z, A): a ray out of the guide carries none
        nf = _near_field_table_cached(rel, np.asarray(zone_lo, float), np.asarray(zone_hi, float), psi, w_ray,
                                      float(aperture_m))
        x, w = np.polynomial.legendre.leggauss(int(elevations))
        x, w = 0.5 * (x + 1.0), 0.5 * w  # on [0, 1]
        xd, wd = np.polynomial.legendre.leggauss(max(1, int(elevations) // DIST_DIVISOR))
        xd, wd = 0.5 * (xd + 1.0), 0.5 * wd
        scatter = {}
        if EDGE_SCATTER:
            wg = scene.waveguide
            tab = _scatter_tables_cached(lx, ly, float(wg.thickness_m), xy[:, 0, 0, :], ang, ray_length, cos_wall,
                                         cos_sensor, width / A, math.radians(scene.sensor.fov_deg), float(wg.n1))
            h = float(node_width_s) if node_width_s else 0.1 * float(scene.sensor.bin_width_s)
            per_m = SCATTER_MAX_N1 / (SPEED_OF_LIGHT_M_PER_S * h)  # time nodes per metre of path at the slowest light
            off = int(math.ceil(-min(SCATTER_MIN_M, 0.0) * per_m)) + 2
            scatter = {f"sc_{k}": jnp.asarray(v, dtype) for k, v in tab.items()} | {"sc_terms": _scatter_terms()}
            scatter |= {"sc_off": off, "sc_nodes": off + int(math.ceil((SCATTER_MIN_M + SCATTER_BINS * SCATTER_BIN_M) * per_m)) + 2}
        groups = {}
        if EDGE_SECOND_GROUPS:
            member, g_normal = _wall_groups(np.asarray(wall_normal, float), ray_length)
            groups = {"es_groups": jnp.asarray(member, dtype), "es_normal": jnp.asarray(g_normal, dtype)}
            if EDGE_SECOND_EXACT_VIEW:
                hit = xy + ray_length[..., None] * np.stack([c, s], -1)  # (S, Z, A, 2) the rays' wall points
                seg = _ray_segment(np, ray_length, width / A, cos_wall)
                groups["es_view"] = jnp.asarray(_wall_group_views(member, g_normal, hit, seg, np.asarray(wall_normal, float),
                                                                  lx, ly), dtype)
        segs = _wall_segments(lx, ly, xy[..., 0] + np.minimum(tx, ty) * c, xy[..., 1] + np.minimum(tx, ty) * s,
                              float(scene.waveguide.thickness_m))
        return cls(
            cos_sensor=jnp.asarray(cos_sensor, dtype),
            cos_wall=jnp.asarray(cos_wall, dtype),
            sensor_normal=jnp.asarray(normals, dtype),
            wall_normal=jnp.asarray(wall_normal, dtype),
            dphi=jnp.asarray(width / A, dtype),
            x=jnp.asarray(x, dtype),
            wx=jnp.asarray(w, dtype),
            xd=jnp.asarray(xd, dtype),
            wxd=jnp.asarray(wd, dtype),
            fov=math.radians(scene.sensor.fov_deg),
            thickness_m=float(scene.waveguide.thickness_m),
            aperture_m=float(aperture_m),
            skin=skin,
            perimeter_m=float(2.0 * (lx + ly)),
            forward_m=mean_forward_distance(lx, ly),
            **{k: jnp.asarray(v, dtype) for k, v in nf.items()},
            edge_mix=jnp.asarray(_edge_mixing(rel, np.asarray(zone_lo, float), np.asarray(zone_hi, float), cos_sensor,
                                              float(aperture_m), ray_length), dtype),
            **{k: jnp.asarray(v, dtype) if k != "ray_seg" else jnp.asarray(v) for k, v in segs.items()},
            ms_c2d=jnp.asarray(double_scatter_coupling(ang, width / A, ray_length > 0), dtype),
            **scatter,
            **groups,
            **({k: jnp.asarray(v, dtype) for k, v in _first_hit_shares(segs, xy[:, 0, 0, :], ang, ray_length).items()}
               if REVERB_SCATTER_SHARE else {}),
        )


def _wall_groups(normals, L) -> tuple[np.ndarray, np.ndarray]:
    """The second bounce's sources (:func:`_edge_second`): each zone's live rays grouped by the wall they end on
    (``normals`` (S, Z, A, 2) their walls' inward normals, ``L`` (S, Z, A) their lengths, 0 for a dead ray), as
    (S, I, Z, A) memberships, 0 or 1: per sensor its zones' groups in order (a zone's middle ray's wall first), ``I``
    the most any sensor has (the others' last ones empty); and each group's wall's inward normal (S, I, 2; 0 for an
    empty one)."""
    S, Z, A = L.shape
    wid = np.round(normals[..., 0] * 2 + normals[..., 1] * 3).astype(int)  # one integer per wall
    groups = [[(z, w) for z in range(Z) for w in dict.fromkeys([wid[s, z, A // 2]] + list(wid[s, z][L[s, z] > 0]))
               if ((wid[s, z] == w) & (L[s, z] > 0)).any()] for s in range(S)]
    out = np.zeros((S, max(1, max(len(g) for g in groups)), Z, A))
    normal = np.zeros(out.shape[:2] + (2,))
    for s in range(S):
        for i, (z, w) in enumerate(groups[s]):
            out[s, i, z] = (wid[s, z] == w) & (L[s, z] > 0)
            normal[s, i] = normals[s, z][wid[s, z] == w][0]
    return out, normal


def _ray_segment(xp, L, dphi, cos_wall):
    """Each ray's stretch of wall (S, Z, A): its length ``L`` times its zone's angle ``dphi`` (Z,) over the wall's
    ``cos`` (floored at 0.1, a grazing ray). ``xp``: numpy at build, jax.numpy in a traced model."""
    return L * dphi[None, :, None] / xp.maximum(cos_wall, 0.1)


def _sin_from_normal(xp, v, t, n):
    """``sin`` of the in-plane angle of ``v`` (..., 2) from a wall's inward normal ``n`` (``t`` its tangent), the
    exact point-to-segment view's ingredient; a ``v`` behind the wall: +-1. ``xp``: numpy or jax.numpy."""
    along, ahead = xp.sum(v * t, -1), xp.sum(v * n, -1)
    return xp.where(ahead > 0, along / xp.sqrt(along**2 + xp.maximum(ahead, 0.0) ** 2 + 1e-30), xp.sign(along))


def _wall_group_views(member, g_normal, hit, seg, normal, lx: float, ly: float) -> np.ndarray:
    """The share of each second-bounce source's diffuse in-plane emission that each ray's wall segment receives
    (:data:`EDGE_SECOND_EXACT_VIEW`), (S, Z, A, I): a source is its group's stretch of wall (``member`` (S, I, Z, A),
    from :func:`_wall_groups`; ``g_normal`` (S, I, 2) its wall's inward normal), from the first to the last of its rays'
    segments, lit evenly; a ray's segment is ``seg`` (S, Z, A) long about its wall point ``hit`` (S, Z, A, 2) on the
    wall of inward normal ``normal``. Both are clipped to the guide's outline (a segment can reach past a corner). By
    Hottel's crossed strings, exact in the plane for two straight stretches of a convex outline; one wall exchanges
    nothing."""
    def tangent(n):
        return np.stack([n[..., 1], -n[..., 0]], -1)

    def clip(p):
        return np.stack([np.clip(p[..., 0], 0.0, lx), np.clip(p[..., 1], 0.0, ly)], -1)

    S, I = member.shape[:2]
    t_g = tangent(g_normal)  # (S, I, 2)
    u = np.einsum("szac,sic->siza", hit, t_g)  # (S, I, Z, A) each ray's point along each group's wall
    on = member > 0
    lo = np.where(on, u - 0.5 * seg[:, None], np.inf).min(axis=(2, 3))  # (S, I)
    hi = np.where(on, u + 0.5 * seg[:, None], -np.inf).max(axis=(2, 3))
    ref = np.einsum("sizac,siza->sic", np.broadcast_to(hit[:, None], (S, I) + hit.shape[1:]), on / np.maximum(
        on.sum(axis=(2, 3), keepdims=True), 1))  # (S, I, 2) a point on the group's wall (its rays' mean point)
    u_ref = np.einsum("sic,sic->si", ref, t_g)
    live = on.any(axis=(2, 3))
    lo, hi = np.where(live, lo, u_ref), np.where(live, hi, u_ref)
    a1 = clip(ref + (lo - u_ref)[..., None] * t_g)  # (S, I, 2)
    a2 = clip(ref + (hi - u_ref)[..., None] * t_g)
    t_r = tangent(normal)  # (S, Z, A, 2)
    b1, b2 = clip(hit - 0.5 * seg[..., None] * t_r), clip(hit + 0.5 * seg[..., None] * t_r)

    def dist(a, b):  # a (S, I, 2), b (S, Z, A, 2) -> (S, Z, A, I)
        return np.sqrt(np.sum((b[:, :, :, None, :] - a[:, None, None, :, :]) ** 2, -1))

    strings = np.abs(dist(a1, b2) + dist(a2, b1) - dist(a1, b1) - dist(a2, b2))
    length = np.sqrt(np.sum((a2 - a1) ** 2, -1))[:, None, None, :]  # (S, 1, 1, I)

    def sin_psi(b):  # a point source at the group's point (a stretch of no length): sin of the angle from its normal
        return _sin_from_normal(np, b[:, :, :, None, :] - ref[:, None, None, :, :], t_g[:, None, None], g_normal[:, None, None])

    point = 0.5 * np.abs(sin_psi(b2) - sin_psi(b1))
    other = np.einsum("szac,sic->szai", normal, g_normal) < 0.5
    share = np.where(length > 1e-9, 0.5 * strings / np.maximum(length, 1e-300), point)
    return np.where(other & live[:, None, None, :], share, 0.0)


def _wall_segments(lx: float, ly: float, wx, wy, thickness: float) -> dict:
    """The guide's four walls cut into ``REVERB_SEGMENTS_PER_WALL`` segments each (counter-clockwise from the
    origin): lengths, the centre-to-centre distances, the share of each one's diffuse in-plane emission each other
    receives (:data:`REVERB_STRINGS`), and the segment each ray's wall point ``(wx, wy)`` lies in (on its own wall:
    the nearest centre could be a neighbouring wall's near a corner)."""
    m = int(REVERB_SEGMENTS_PER_WALL)
    u = (np.arange(m) + 0.5) / m
    walls = [  # (centres, inward normal, length)
        (np.stack([u * lx, 0 * u], -1), (0.0, 1.0), lx), (np.stack([0 * u + lx, u * ly], -1), (-1.0, 0.0), ly),
        (np.stack([(1 - u) * lx, 0 * u + ly], -1), (0.0, -1.0), lx), (np.stack([0 * u, (1 - u) * ly], -1), (1.0, 0.0), ly)]
    centres = np.concatenate([w[0] for w in walls])
    normals = np.concatenate([np.tile(w[1], (m, 1)) for w in walls])
    lengths = np.concatenate([np.full(m, w[2] / m) for w in walls])
    d = centres[None, :, :] - centres[:, None, :]  # from k to l
    r = np.sqrt(np.sum(d**2, -1) + thickness**2)
    pts = np.stack([np.asarray(wx, float), np.asarray(wy, float)], -1)
    tangents = np.stack([normals[:, 1], -normals[:, 0]], -1)
    rel = pts[..., None, :] - centres  # (..., M, 2): the segment holding each point (0 there; the nearest outside)
    near = np.argmin(np.maximum(np.abs(np.sum(rel * tangents, -1)) - 0.5 * lengths, 0.0)
                     + np.abs(np.sum(rel * normals, -1)), axis=-1)
    if REVERB_STRINGS:  # Hottel's crossed strings: the exact in-plane exchange of two straight segments of a convex outline
        a1, a2 = centres - 0.5 * lengths[:, None] * tangents, centres + 0.5 * lengths[:, None] * tangents
        dist = lambda a, b: np.sqrt(np.sum((a[:, None, :] - b[None, :, :]) ** 2, -1))  # noqa: E731  (k, l)
        crossed = dist(a1, a1) + dist(a2, a2)  # (k, l): segment k's ends to segment l's (both counter-clockwise)
        uncrossed = dist(a2, a1) + dist(a1, a2)
        view = np.maximum(crossed - uncrossed, 0.0) / (2.0 * lengths[:, None])
        view = np.where(normals @ normals.T > 0.5, 0.0, view)  # one wall: nothing (not rounding's 1e-16)
    else:  # from the centres: cos at the source times cos at the receiver (0 on one wall), len_l / (2 r)
        cc = np.clip(np.sum(d * normals[:, None], -1) / r, 0, 1) * np.clip(-np.sum(d * normals[None], -1) / r, 0, 1)
        view = cc * lengths[None, :] / (2.0 * r)
    return {"seg_len": lengths, "seg_r": r, "seg_view": view, "ray_seg": near.astype(np.int32), "seg_xy": centres,
            "seg_tan": tangents}


def _first_hit_shares(segs: dict, xy, ang, L) -> dict:
    """Where the beam's light scattered into the guided band first meets the walls (NumPy; :data:`REVERB_SCATTER_SHARE`):
    each wall segment's share ``hs_share`` (S, Z, A, M) of each ray's scattered light (its points, ``SCATTER_SHARE_POINTS``
    evenly along the ray, send ``theta_m / (2 pi)`` of their in-plane isotropic light to segment ``m``, the angle it
    subtends; the shares of a point sum to 1), and per sensor and segment the mean range ``hs_x`` where that light
    scattered and its mean in-plane distance ``hs_r`` to the segment's centre (weighted by the shares and each ray's
    length, as its scattered light is). The attenuation along the ray is left out of the weights. ``segs``: the
    field's wall segments (:func:`_wall_segments`)."""
    c, t, h = segs["seg_xy"], segs["seg_tan"], 0.5 * segs["seg_len"][:, None]
    a1, a2 = c - h * t, c + h * t  # (M, 2) the segments' ends
    S, Z, A = L.shape
    NP = int(SCATTER_SHARE_POINTS)
    u = (np.arange(NP) + 0.5) / NP
    x = np.asarray(L, float)[..., None] * u  # (S, Z, A, NP)
    P = np.asarray(xy, float)[:, None, None, None, :] + x[..., None] * np.stack([np.cos(ang), np.sin(ang)], -1)[..., None, :]
    d1, d2 = a1 - P[..., None, :], a2 - P[..., None, :]  # (S, Z, A, NP, M, 2)
    theta = np.abs(np.arctan2(d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0], np.sum(d1 * d2, -1)))
    share = theta / (2.0 * np.pi)  # (S, Z, A, NP, M)
    mid = 0.5 * (a1 + a2)
    rho = np.sqrt(np.sum((mid - P[..., None, :]) ** 2, -1))  # to the segment's centre
    live = (np.asarray(L) > 0)[..., None, None]
    w = share * live * np.asarray(L, float)[..., None, None]
    ws = np.sum(w, axis=(1, 2, 3))  # (S, M)
    safe = np.where(ws > 0, ws, 1.0)
    return {"hs_share": np.mean(share * live, axis=3),
            "hs_x": np.where(ws > 0, np.sum(w * x[..., None], axis=(1, 2, 3)) / safe, 0.0),
            "hs_r": np.where(ws > 0, np.sum(w * rho, axis=(1, 2, 3)) / safe, 0.0)}


def mean_forward_distance(lx: float, ly: float, n: int = 64) -> float:
    """Mean distance from a point of an ``lx`` x ``ly`` rectangle to its walls along a direction, both uniform
    (midpoint rule, ``n`` points per side and ``n`` directions): how much later the light inside a diffuse
    field reaches the walls than it is there (0.142 m in a 30 cm square, 1.21x half its mean chord; ``n`` = 64 is
    within 1e-4 of 256)."""
    u = (np.arange(n) + 0.5) / n
    x, y = np.meshgrid(u * lx, u * ly, indexing="ij")
    th = 2.0 * np.pi * u
    return float(np.mean(np.minimum(*_to_walls(lx, ly, x, y, np.cos(th)[:, None, None], np.sin(th)[:, None, None]))))


def _to_walls(lx: float, ly: float, x, y, c, s):
    """Distances from ``(x, y)`` inside an ``lx`` x ``ly`` rectangle along the direction ``(c, s)`` to its x walls
    and to its y walls (inf along the other axis); NumPy, broadcast."""
    with np.errstate(divide="ignore", invalid="ignore"):
        tx = np.where(c > 1e-12, (lx - x) / c, np.where(c < -1e-12, -x / c, np.inf))
        ty = np.where(s > 1e-12, (ly - y) / s, np.where(s < -1e-12, -y / s, np.inf))
    return tx, ty


def _wall_hit(tx, ty, c, s):
    """Where rays along ``(c, s)`` meet the walls, from :func:`_to_walls`' distances ``tx``, ``ty``: the cosine of
    their incidence on the wall they hit and its inward normal (..., 2); NumPy, broadcast."""
    x_wall = tx <= ty
    normal = np.stack([np.where(x_wall, -np.sign(c), 0.0), np.where(x_wall, 0.0, -np.sign(s))], -1)
    return np.where(x_wall, np.abs(c), np.abs(s)), normal


def inward_normals(scene: Scene) -> np.ndarray:
    """Inward unit normal of the edge each sensor sits on (S, 2); at a corner, the one nearer its axis
    (the Monte Carlo launches from the same normals)."""
    lx, ly = scene.waveguide.size_m
    out = []
    for sp in scene.sensors:
        x, y = sp.position_m
        a = math.radians(sp.direction_deg)
        cands = [(abs(x), (1.0, 0.0)), (abs(x - lx), (-1.0, 0.0)), (abs(y), (0.0, 1.0)), (abs(y - ly), (0.0, -1.0))]
        near = [nrm for dist, nrm in cands if dist <= 1e-6] or [min(cands)[1]]
        out.append(max(near, key=lambda nrm: nrm[0] * math.cos(a) + nrm[1] * math.sin(a)))
    return np.array(out, float)


class _Elev(NamedTuple):
    mu: jax.Array  # (J,) return elevations (positive half; the band is symmetric)
    c: jax.Array  # (J,) their cosines
    dmu: jax.Array  # (J,) weights over the whole band (both signs)
    c_out: jax.Array  # outbound cosine (RMS of the launched beam)
    mu_out: jax.Array  # mean |mu| of the launched beam


def launch_band(n1, fov_rad: float):
    """The guided band and the launched beam in a slab of index ``n1`` (air outside), lit by a beam of
    full angle ``fov_rad``: ``(cg, launch, c_out)``, ``cg = sqrt(1 - 1/n1^2)`` the largest guided
    ``|mu|`` (``mu = sin`` elevation), ``launch = min(sin(fov/2) / n1, cg)`` the launched beam's (a round
    beam refracted at the edge) and ``c_out = sqrt(1 - launch^2 / 3)`` its RMS cosine. The one place
    these are computed (the model's elevations, the inversion's range speed); JAX values (traced
    included) give JAX values, floats and NumPy values give NumPy values."""
    xp = jnp if isinstance(n1, jax.Array) else np
    cg = xp.sqrt(xp.maximum(1.0 - 1.0 / n1**2, 1e-12))
    launch = xp.minimum(math.sin(0.5 * fov_rad) / n1, cg)
    return cg, launch, xp.sqrt(1.0 - launch**2 / 3.0)


def _band_inv_cos(cg):
    """The mean ``1 / cos`` of light spread uniformly in ``mu`` over the guided band ``|mu| < cg`` (isotropically
    scattered light that stays guided): ``asin(cg) / cg``; NumPy or JAX, as ``cg``."""
    xp = jnp if isinstance(cg, jax.Array) else np
    return xp.arcsin(cg) / cg


def _elevations(gg: GuidedGeometry, n1, distributed: bool = False) -> _Elev:
    cg, launch, c_out = launch_band(jnp.asarray(n1), gg.fov)
    x, wx = (gg.xd, gg.wxd) if distributed else (gg.x, gg.wx)
    mu = cg * x
    return _Elev(mu=mu, c=jnp.sqrt(1.0 - mu**2), dmu=2.0 * cg * wx, c_out=c_out, mu_out=0.5 * launch)


def _beam_at_wall(gg: "GuidedGeometry", el: _Elev, L, mu_t):
    """The share of the launched light each ray (S, Z, A) carries to its far wall: ``dphi / fov exp(-mu_t L /
    c_out)``."""
    return gg.dphi[None, :, None] / gg.fov * jnp.exp(-mu_t * L / el.c_out)


def _mean_cos(el: _Elev):
    """The band's mean in-plane cosine (uniform in ``mu``): the field's mean in-plane speed over ``c1``."""
    return jnp.sum(el.dmu * el.c) / jnp.sum(el.dmu)


def _wall_band(el: _Elev):
    """A Lambertian wall's guided emission: the share ``G = (2/pi) int sqrt(1 - mu^2) dmu`` of it the band guides,
    and its flux-weighted mean ``1 / cos``."""
    flux = jnp.sum(el.dmu * el.c)
    return flux * (2.0 / math.pi), jnp.sum(el.dmu * el.c / el.c) / flux


def _wall_band_var(el: _Elev):
    """The variance of ``1 / cos`` over a Lambertian wall's guided emission (the weights of :func:`_wall_band`'s
    mean): how much a wall-to-wall leg's delay spreads, relative to its length."""
    flux = jnp.sum(el.dmu * el.c)
    mean = jnp.sum(el.dmu) / flux
    return jnp.maximum(jnp.sum(el.dmu / el.c) / flux - mean**2, 0.0)


def _blur(var_nodes, n: int):
    """The transform of a Gaussian of variance ``var_nodes`` (in nodes squared, any shape) at the ``n // 2 + 1``
    frequencies of an ``rfft`` of ``n`` nodes: ``var_nodes.shape + (F,)``, real."""
    w2 = jnp.asarray((2.0 * np.pi * np.arange(n // 2 + 1) / n) ** 2, var_nodes.dtype)
    return jnp.exp(-0.5 * var_nodes[..., None] * w2)


def _weighted_step(times, weights, nodes: Nodes):
    """Running share of ``weights`` of events at ``times`` (S, Z', E) before each node (cf. step_on)."""
    w = deposit(times, weights, nodes)
    return jnp.cumsum(w, axis=-1) - 0.5 * w


def _coupling(skin, strength):
    """The share of each contact's area in optical contact: the skin's ``coupling`` times the contact's
    ``strength``, at most 1 (a strength above 1 is a contact coupling more than the skin model's typical
    one, up to full optical contact at ``1 / coupling``)."""
    return jnp.clip(skin.coupling * strength, 0.0, 1.0)


def _frustrated(hits, q):
    """Share of light frustrated over a chord with ``hits`` expected top-face hits (``chord |mu| / (2 h
    cos)``), each frustrating ``q`` (``coupling (1 - R_Fresnel)``).

    With ``DISCRETE_HITS`` (see there) the hits are discrete, spaced ``2 h cos / |mu|`` along the chord
    from a uniformly random first one: ``floor(x)`` or ``floor(x) + 1`` of them, so the transmission is
    ``(1 - q)^floor(x) (1 - frac(x) q)``, the straight line between the integers; otherwise
    ``(1 - q)^x``, which frustrates up to ``-ln(1 - q) / q`` times (1.19 at ``q = 0.3``) too much below
    one hit (Jensen), as the Monte Carlo's next-event estimation does."""
    lq = jnp.log1p(-q)
    if not DISCRETE_HITS:
        return -jnp.expm1(hits * lq)
    k = jnp.floor(hits)
    return 1.0 - jnp.exp(k * lq) * (1.0 - (hits - k) * q)


def _disk_chord(rad, across):
    """Length of the chord a line ``across`` from a disk's centre cuts through it (0 beyond the rim), its square
    root kept smooth at the rim (a hair of the radius) so the gradient stays finite."""
    half2 = rad**2 - across**2
    chord = 2.0 * jnp.sqrt(jnp.maximum(half2, 0.0) + (1e-3 * rad) ** 2) - 2e-3 * rad
    return jnp.where(half2 > 0, chord, 0.0)


def _lost_out(p, gg, el, chord, fc):
    """Share of the launched beam (its mean ``|mu|``) frustrated over ``chord`` under a contact coupling ``fc``
    (broadcast to ``chord``)."""
    hits = chord * el.mu_out / (2.0 * gg.thickness_m * el.c_out)
    return _frustrated(hits, fc * (1.0 - _fresnel(p.n1, gg.skin.n, el.mu_out)))


def _lost_back(p, gg, el, chord, fc):
    """Share of the light at each guided elevation (a trailing axis J) frustrated over ``chord`` under a contact
    coupling ``fc`` (broadcast to ``chord``): ``chord |mu| / (2 h cos)`` top-face hits."""
    hits = chord[..., None] * (el.mu / (2.0 * gg.thickness_m * el.c))
    return _frustrated(hits, fc[..., None] * (1.0 - _fresnel(p.n1, gg.skin.n, el.mu)))


def _frustration(ctx, gg: GuidedGeometry, el: _Elev):
    """Skin contacts crossed by each ray: (P_out (S, Z, A, N), P_ret (S, Z, A, N, J), behind (S, Z, A, N),
    dist (S, N)): the share of light entering the skin on the way out and back along the ray's chord,
    and whether the contact lies before the ray's far edge (a smooth step)."""
    p, geom = ctx.params, ctx.geom
    skin = gg.skin
    d = p.touch_xy_m[None, :, :] - geom.sensor_xy[:, None, :]  # (S, N, 2)
    ca, sa = jnp.cos(geom.ray_angle)[..., None], jnp.sin(geom.ray_angle)[..., None]  # (S, Z, A, 1)
    along = d[:, None, None, :, 0] * ca + d[:, None, None, :, 1] * sa  # (S, Z, A, N)
    across = -d[:, None, None, :, 0] * sa + d[:, None, None, :, 1] * ca
    rad = p.touch_radius_m
    chord = jnp.where(along > 0, _disk_chord(rad, across), 0.0)
    fc = _coupling(skin, p.touch_strength)  # (N,)
    P_out = _lost_out(p, gg, el, chord, fc)  # share frustrated over the chord
    P_ret = _lost_back(p, gg, el, chord, fc)
    behind = jax.nn.sigmoid((geom.ray_length[..., None] - along) / rad)  # contact before the far edge
    return P_out * behind, P_ret * behind[..., None], along


def _edge(ctx, gg, el, frus):
    p, geom, nodes = ctx.params, ctx.geom, ctx.nodes
    L = geom.ray_length[..., None]  # (S, Z, A, 1)
    mu_t = p.mu_s_per_m + p.mu_a_per_m
    Lsafe = jnp.maximum(L, 1e-9)
    # Params.end_incidence_power: cos^p on top of this optics' Lambertian edge (p = 0: as before)
    from .components import edge_law

    # per unit power reaching the wall (P1, the beam's share dphi / fov after the outbound attenuation)
    ret = (p.end_reflectance * edge_law(gg.cos_wall, p.end_incidence_power)[..., None] * gg.cos_wall[..., None] * gg.cos_sensor[..., None]
           / (math.pi * gg.thickness_m * jnp.sqrt(Lsafe**2 + (0.5 * gg.aperture_m) ** 2))
           * el.dmu * el.c * jnp.exp(-mu_t * L / el.c))  # (S, Z, A, J)
    ret = jnp.where(L > 0, ret, 0.0)
    P1 = _beam_at_wall(gg, el, geom.ray_length, mu_t)[..., None]
    if frus is not None:
        P_out, P_ret, _ = frus
        ret = ret * jnp.prod(1.0 - P_ret, axis=-2)
        amp_ret = ret * P1  # the second bounce's receiving rays (with skin contacts: their return leg only)
        amp = amp_ret * jnp.prod(1.0 - P_out, axis=-1)[..., None]
    elif ctx.contacts is not None:
        from .components import shadow

        ret = ret * shadow(geom.ray_length, ctx.contacts, p)[..., None]
        amp = amp_ret = ret * P1
    else:
        amp = amp_ret = ret * P1
    t = p.emission_time_s + L * (1.0 / el.c_out + 1.0 / el.c) / nodes.c1
    S, Z = amp.shape[:2]
    if EDGE_APERTURE and gg.edge_mix is not None:
        # each zone's rays take the share of their return inside the zone, its edge rays the neighbours' spill too
        amp = jnp.einsum("szap,spj->szaj", gg.edge_mix, amp.reshape(S, -1, amp.shape[-1]))
    t = jnp.broadcast_to(t, amp.shape).reshape(S, Z, -1)
    amp = amp.reshape(S, Z, -1)
    scatter = EDGE_SCATTER and gg.sc_w is not None  # the first return alone carries the scattered light's kernels
    K = nodes.t.shape[0]
    if scatter:  # the first return past the window dropped (not on to the second's grid), which starts 2 nodes later
        t = jnp.where(t < (K + 1) * nodes.h, t, 4.0 * K * nodes.h)
    if EDGE_SECOND:  # one deposit for both bounces (with the kernels: the second on a grid of its own after the first's)
        t2, a2 = _edge_second(ctx, gg, el, amp_ret, frus)
        t, amp = jnp.concatenate([t, t2 + (K + 2) * nodes.h if scatter else t2], -1), jnp.concatenate([amp, a2], -1)
    if scatter:
        both = deposit(t, amp, nodes._replace(t=jnp.zeros((2 * K + 2,), nodes.t.dtype)))
        first = both[..., :K]
        second = both[..., K + 2:]
        out = first + second + _edge_scatter(ctx, gg, el, first, second if SCATTER_SECOND else None)
    else:
        out = deposit(t, amp, nodes)
    if EDGE_REVERB:
        out = out + _reverb(ctx, gg, el, ret, frus)
    return p.gain[:, None, None] * out


def _edge_scatter(ctx, gg, el, first, second=None):
    """The light the walls and the volume exchange around each zone's lit wall (before the gain; :data:`EDGE_SCATTER`):
    the zone's first return ``first`` (S, Z, K) convolved with its two kernels of :func:`_scatter_tables`. The beam's
    scattered light on the walls: ``mu_s cg / c_out`` per unit of the tables' weight (the guided share of isotropic
    scattering, per metre of in-plane range); the walls' light scattered back: ``mu_s G / cbar^2`` (the guided share
    of a Lambertian wall, the volume view's ``1 / cbar`` and its elevations' ``1 / cbar`` against the first return's).
    Each bin's delay and attenuation are its mean lengths' at the fitted optics: the beam's leg at ``1 / c_out``, the
    diffuse leg at the band's mean ``1 / cos`` losing ``mu_a + mu_s (1 - cg)`` (scattering inside the band only
    redirects it; a leg into the volume at the isotropic band's, :data:`SCATTER_FLUENCE`), the view's leg at the
    band's mean ``1 / cos``. With ``second`` (the far edge's second bounce, (S, Z, K); :data:`SCATTER_SECOND`) term 1's
    kernel is applied to it too: the walls in view re-emit the second bounce's light into the same volume. Contacts act
    through ``first`` and ``second`` alone."""
    p, nodes = ctx.params, ctx.nodes
    cg, c_out = launch_band(p.n1, gg.fov)[0], el.c_out
    g_iso = _band_inv_cos(cg)
    G, g_wall = _wall_band(el)
    cbar = _mean_cos(el)
    mu_t = p.mu_s_per_m + p.mu_a_per_m
    mu_eff = p.mu_a_per_m + p.mu_s_per_m * (1.0 - cg)
    g_back = g_iso if SCATTER_FLUENCE else g_wall  # a wall-to-volume leg (as the tables bin it)
    # per term: the diffuse leg's 1 / cos, what the last leg loses, and the prefactor
    terms = {"beam_to_walls": (g_iso, mu_t, p.mu_s_per_m * cg / c_out),
             "walls_back": (g_back, mu_t, p.mu_s_per_m * G / cbar**2),
             "redirect": (g_back, mu_eff, p.mu_s_per_m * cg * g_wall * p.end_reflectance * G)}  # a diffuse last leg
    legs, last, pref = zip(*(terms[k] for k in gg.sc_terms))
    leg, last, pref = (jnp.stack(v)[:, None] for v in (legs, last, pref))  # (T, 1)
    path = gg.sc_a / c_out + leg * gg.sc_b + g_iso * gg.sc_c  # (S, Z, T, NK)
    att = jnp.exp(-mu_t * gg.sc_a / c_out - last * g_iso * gg.sc_c - mu_eff * leg * gg.sc_b)
    S, Z, K = first.shape
    T = path.shape[2]
    times = path / nodes.c1 + (gg.sc_off + 0.5) * nodes.h  # (S, Z, T, NK) on the kernels' grid
    amp = pref * gg.sc_w * att
    n_k = gg.sc_nodes
    grid = Nodes(t=jnp.zeros((n_k,), first.dtype), h=nodes.h, r=None, dr=None, c1=nodes.c1)
    n = 1 << (K + n_k - 1).bit_length()  # zero-padded (no wrap), a power of two
    if second is None:  # one kernel for the terms together
        kern = deposit(times.reshape(S, Z, -1), amp.reshape(S, Z, -1), grid)  # (S, Z, n_k)
        y = jnp.fft.irfft(jnp.fft.rfft(first, n) * jnp.fft.rfft(kern, n), n)
    else:  # each term's kernel on its own: term 1's sees the second bounce too
        kern = deposit(times.reshape(S, Z * T, -1), amp.reshape(S, Z * T, -1), grid).reshape(S, Z, T, n_k)
        kf = jnp.fft.rfft(kern, n)
        back = gg.sc_terms.index("walls_back")
        y = jnp.fft.irfft(jnp.fft.rfft(first, n) * jnp.sum(kf, 2) + jnp.fft.rfft(second, n) * kf[:, :, back], n)
    return y[..., gg.sc_off:gg.sc_off + K]


def _edge_second(ctx, gg, el, amp1, frus):
    """The far edge's second diffuse bounce inside the lit footprint (before the gain).

    Each ray's wall segment (length ``L dphi / cos_wall``) is lit by the beam with power
    ``P_i = dphi / fov exp(-mu_t L / c_out)`` and reflects ``R P_i`` diffusely; the guided share ``G``
    (``(2/pi) int |mu|<mu_g sqrt(1 - mu^2) dmu``) spreads in the plane as ``cos(psi) / 2`` per radian,
    so segment ``j`` receives ``R P_i G cos_i cos_j len_j / (2 r_ij)`` (attenuated over ``r_ij`` at
    the band's mean ``1 / cos``) and returns it like its first bounce: the first-bounce amplitude
    ``amp1_j`` times ``P2_j / P_j``, delayed by the middle leg. The same wall exchanges nothing
    (``cos = 0``); near a corner it is the main part. Sources: one per zone and wall (:data:`EDGE_SECOND_GROUPS`), or
    the middle ray of every ``EDGE_SECOND_STRIDE``.
    The return leg travels at each return elevation's speed (``EDGE_SECOND_SPREAD`` groups of them, weighted as
    the first bounce's return), so it spreads in time as the first bounce does."""
    p, geom, nodes = ctx.params, ctx.geom, ctx.nodes
    L = geom.ray_length  # (S, Z, A)
    S, Z, A = L.shape
    mu_t = p.mu_s_per_m + p.mu_a_per_m
    u = jnp.stack([jnp.cos(geom.ray_angle), jnp.sin(geom.ray_angle)], -1)
    W = geom.sensor_xy[:, None, None, :] + L[..., None] * u  # (S, Z, A, 2) wall points
    beam = _beam_at_wall(gg, el, L, mu_t)  # (S, Z, A)
    if EDGE_SECOND_GROUPS and gg.es_groups is not None:  # a source per zone and wall: its rays' power-weighted centre
        m = gg.es_groups  # (S, I, Z, A)
        Pg = jnp.einsum("siza,sza->si", m, beam)
        wts = m * beam[:, None] / jnp.where(Pg > 0, Pg, 1.0)[..., None, None]
        Ws = jnp.einsum("siza,szac->sic", wts, W)
        Ls = jnp.einsum("siza,sza->si", wts, L)
        ns = gg.es_normal
        Ps = Pg if frus is None else jnp.einsum("siza,sza->si", m, beam * jnp.prod(1.0 - frus[0], axis=-1))
    else:
        k = max(1, min(int(EDGE_SECOND_STRIDE), A))
        sel = slice(k // 2, None, k)  # the middle ray of every k (a zone's middle one at k = A)
        Ws, ns, Ls = W[:, :, sel].reshape(S, -1, 2), gg.wall_normal[:, :, sel].reshape(S, -1, 2), L[:, :, sel].reshape(S, -1)
        Ps = (A / len(range(A)[sel]) * beam)[:, :, sel]  # (S, Z, A/k): each source stands for its k rays
        if frus is not None:
            Ps = Ps * jnp.prod(1.0 - frus[0], axis=-1)[:, :, sel]
        Ps = Ps.reshape(S, -1)
    d = W[:, :, :, None, :] - Ws[:, None, None, :, :]  # (S, Z, A, I, 2): from source i to receiver j
    G, inv_c = _wall_band(el)  # guided share of a Lambertian wall's emission, its mean 1 / cos
    P1 = jnp.maximum(beam, 1e-300)
    if EDGE_SECOND_EXACT_VIEW and EDGE_SECOND_GROUPS and gg.es_view is not None:
        view = gg.es_view  # (S, Z, A, I): the groups' stretches to the rays' segments, built once
        r = jnp.sqrt(jnp.sum(d**2, -1) + 1e-12)
    elif EDGE_SECOND_EXACT_VIEW:
        seg = _ray_segment(jnp, L, gg.dphi, gg.cos_wall)  # (S, Z, A) receiving segment length
        nj = gg.wall_normal[:, :, :, None, :]  # (S, Z, A, 1, 2)
        half = 0.5 * seg[..., None, None] * jnp.stack([nj[..., 1], -nj[..., 0]], -1)  # half the segment along its wall
        ni = ns[:, None, None]  # (S, 1, 1, I, 2)
        ti = jnp.stack([ni[..., 1], -ni[..., 0]], -1)
        other = jnp.sum(ni * nj, -1) < 0.5  # one wall exchanges nothing
        view = jnp.where(other, 0.5 * jnp.abs(_sin_from_normal(jnp, d + half, ti, ni) - _sin_from_normal(jnp, d - half, ti, ni)),
                         0.0)  # (S, Z, A, I)
        r = jnp.sqrt(jnp.sum(d**2, -1) + 1e-12)
    else:
        seg = _ray_segment(jnp, L, gg.dphi, gg.cos_wall)  # (S, Z, A) receiving segment length
        r = jnp.sqrt(jnp.sum(d**2, -1) + gg.thickness_m**2)
        cos_i = jnp.clip(jnp.sum(d * ns[:, None, None], -1) / r, 0.0, 1.0)
        cos_j = jnp.clip(-jnp.sum(d * gg.wall_normal[:, :, :, None, :], -1) / r, 0.0, 1.0)
        view = 0.5 * cos_i * cos_j * seg[..., None] / r  # (S, Z, A, I) the share a receiving segment gets of a source
    ratio = (p.end_reflectance * G * Ps[:, None, None, :] * view / P1[..., None]
             * jnp.exp(-mu_t * r * inv_c))  # (S, Z, A, I)
    if frus is not None and EDGE_SECOND_SHADOW:
        ratio = ratio * _leg_transmission(ctx, gg, el, Ws, d)
    if EDGE_SECOND_SPREAD:
        E = amp1.shape[-1]
        member = np.zeros((E, min(int(EDGE_SECOND_SPREAD), E)))  # return elevation -> its group: one product, not a sum each
        for j, g in enumerate(np.array_split(np.arange(E), member.shape[1])):
            member[g, j] = 1.0
        member = jnp.asarray(member, amp1.dtype)
        ag = amp1 @ member  # (S, Z, A, n)
        lg = (amp1 / el.c) @ member / jnp.where(ag > 0, ag, 1.0)
        amp = ag[..., None, :] * ratio[..., None]  # (S, Z, A, I, n)
        t = p.emission_time_s + ((Ls[:, None, None, :] / el.c_out + r * inv_c)[..., None]
                                 + (L[..., None] * lg)[..., None, :]) / nodes.c1
    else:
        a1 = jnp.sum(amp1, -1)  # (S, Z, A) first-bounce amplitude, all return elevations
        amp = a1[..., None] * ratio
        t = p.emission_time_s + (Ls[:, None, None, :] / el.c_out + r * inv_c + L[..., None] * inv_c) / nodes.c1
    return t.reshape(S, Z, -1), amp.reshape(S, Z, -1)


#: the variance of :func:`_shifts`'s (and :func:`deposit`'s) quadratic B-spline, in nodes squared, wherever the mass sits
#: (lower case: a constant, not one of the module's switches)
_spline_var = 0.25


def _shifts(u, n: int):
    """The discrete transform of a unit mass at position ``u`` (in nodes) on a periodic grid of ``n`` nodes, spread
    with :func:`deposit`'s quadratic B-spline weights (mass and mean time kept, differentiable in ``u``), at the
    ``n // 2 + 1`` frequencies of an ``rfft``: real and imaginary parts, ``u.shape + (F,)``. From a table of the
    grid's phases (a constant) and the spline's three weights: no complex exponential per mass and frequency (those
    cost the CPU ten times more), no scatter, no FFT."""
    F = n // 2 + 1
    ang = 2.0 * np.pi * np.outer(np.arange(n), np.arange(F)) / n
    centre = jnp.round(u)
    d = (u - centre)[..., None]
    i = centre.astype(jnp.int32) % n
    c1, s1 = jnp.asarray(np.cos(ang[1]), u.dtype), jnp.asarray(np.sin(ang[1]), u.dtype)  # one node's phase
    br = (0.75 - d**2) + (0.25 + d**2) * c1  # b0 + b- e^{+ia} + b+ e^{-ia}: b- + b+ = 1/4 + d^2, b- - b+ = -d
    bi = -d * s1
    tr, ti = jnp.asarray(np.cos(ang), u.dtype)[i], jnp.asarray(-np.sin(ang), u.dtype)[i]
    return tr * br - ti * bi, tr * bi + ti * br


def _cmv(ar, ai, xr, xi, spec: str):
    """A complex product ``einsum(spec, a, x)`` from real parts (XLA's CPU complex products are twice as slow)."""
    e = lambda a, x: jnp.einsum(spec, a, x)  # noqa: E731
    return e(ar, xr) - e(ai, xi), e(ar, xi) + e(ai, xr)


def _geometric_tail(ar, ai, br, bi):
    """The fifth bounce on from the fourth (``a``) and fifth (``b``), (F, S, M) real and imaginary parts: after a
    few bounces the field is diffuse and each further bounce multiplies it by one ratio per frequency and sensor,
    ``rho = <a, b> / <a, a>`` (least squares: the fifth on the fourth; its phase is the mean delay of a bounce, its
    modulus the share a bounce keeps, capped at 0.99), so the fifth on sum to ``b / (1 - rho)``: two matrix-vector
    products per frequency instead of summing the orders (against 512 orders summed one by one in a clear 10 cm
    square the field is within 0.1% / 0.4% / 0.9% / 3.8% for walls of reflectance 0.3 / 0.6 / 0.9 / 1)."""
    # rho is unchanged when a and b are scaled alike: scaled to a's largest part first, so that neither <a, a> nor its
    # derivatives under- or overflow for a field of any size (float32 models included)
    scale = jax.lax.stop_gradient(jnp.max(jnp.maximum(jnp.abs(ar), jnp.abs(ai)), axis=-1, keepdims=True))
    scale = jnp.where(scale > 0, scale, 1.0)
    ur, ui, vr, vi = ar / scale, ai / scale, br / scale, bi / scale
    den = jnp.sum(ur**2 + ui**2, axis=-1, keepdims=True)
    safe = jnp.where(den > 0, den, 1.0)
    rr = jnp.where(den > 0, jnp.sum(ur * vr + ui * vi, axis=-1, keepdims=True) / safe, 0.0)
    ri = jnp.where(den > 0, jnp.sum(ur * vi - ui * vr, axis=-1, keepdims=True) / safe, 0.0)
    m2 = rr**2 + ri**2
    cap = jnp.where(m2 > 0.99**2, 0.99 * jax.lax.rsqrt(jnp.maximum(m2, 0.99**2)), 1.0)
    qr, qi = 1.0 - rr * cap, -ri * cap  # 1 - rho, |.| >= 0.01
    q2 = qr**2 + qi**2
    return (br * qr + bi * qi) / q2, (bi * qr - br * qi) / q2


def _field_leg_transmission(ctx, gg, el):
    """Share of each wall-to-wall leg of the reverberant field (segment k -> l, (M, M)) that crosses every contact
    unfrustrated. A leg is a bundle of rays from segment k's length to segment l's, as wide across its direction as
    their projections (interpolated along it); a contact of radius ``a`` at distance ``e`` across the leg's line
    is crossed by the share ``2 a / w`` of it (while ``|e| < w / 2``, a smooth step one radius wide; beyond either
    end of the leg, nothing), each such ray frustrated over the mean chord ``pi a / 2`` (its top-face hits per
    guided elevation, averaged with a Lambertian wall's guided weights: :func:`_wall_light_frustrated`)."""
    p = ctx.params
    rad = p.touch_radius_m  # (N,)
    src = gg.seg_xy[:, None, :]
    length, u, along, across = _leg_frame(p, src, gg.seg_xy[None, :, :] - src)  # (M, M), (M, M, N)
    s = jnp.clip(along / length[..., None], 0.0, 1.0)
    proj = lambda t: jnp.abs(t[..., 0] * u[..., 1] - t[..., 1] * u[..., 0])  # noqa: E731  width across the leg
    wk = (gg.seg_len[:, None] * proj(gg.seg_tan[:, None, :]))[..., None]
    wl = (gg.seg_len[None, :] * proj(gg.seg_tan[None, :, :]))[..., None]
    width = jnp.maximum((1.0 - s) * wk + s * wl, 2.0 * rad)  # (M, M, N)
    inside = (jax.nn.sigmoid(along / rad) * jax.nn.sigmoid((length[..., None] - along) / rad)
              * jax.nn.sigmoid((0.5 * width - jnp.abs(across)) / rad))
    lost = _wall_light_frustrated(p, gg, el, 0.5 * math.pi * rad) * 2.0 * rad / width * inside  # (M, M, N)
    return jnp.prod(1.0 - jnp.minimum(lost, 1.0), axis=-1)


def _reverb(ctx, gg, el, ret, frus):
    """The walls' later diffuse bounces (before the gain): a time-resolved radiosity of the guide's walls.

    The walls are cut into segments (``REVERB_SEGMENTS_PER_WALL`` each). Segment ``k`` reflecting power ``R H``
    diffusely sends segment ``l`` the share ``F_kl = G cos_k cos_l len_l / (2 r_kl) exp(-mu_eff r_kl <1/cos>)``
    (the guided share ``G`` of a Lambertian wall spread in the plane as ``cos / 2`` per radian, as in
    :func:`_edge_second`) after ``r_kl <1/cos> / c1``; scattering inside the guided band only redirects the field's
    light between walls, so the legs lose ``mu_eff = mu_a + mu_s (1 - cg)``. The beam lights its rays' segments
    (``P_i = dphi / fov exp(-mu_t L / c_out)`` at ``L / (c_out c1)``, past any contact's frustration); the first
    bounce's return is :func:`_edge`'s and the second's, inside the lit footprint, :func:`_edge_second`'s, so the
    field counts the irradiance of the third bounce on: ``(I - T)^-1 T^2 H1`` with ``T = R F``, per frequency
    (each leg's delay spread on the grid like a deposit, :func:`_shifts`): the third, fourth and fifth bounces
    explicitly, the later ones as a geometric train (:func:`_geometric_tail`). The beam's light scattered on its way
    out (share ``cg`` of it into the guided band, isotropic) lights the walls where the geometry sends it, at its mean
    first-hit delay per segment (:data:`REVERB_SCATTER_SHARE`; off: evenly, when the beam reaches its wall): as the
    third bounce's irradiance, or, with :data:`EDGE_SCATTER` (whose kernels see its first wall hit where the zones see
    the walls), as the second's, so that the field counts it from its second wall hit on.
    Each ray's wall segment (``L dphi / cos_wall`` of its segment's irradiance per metre) reflects it like its first
    bounce: ``ret`` (S, Z, A, J), the first bounce's counts per unit power on the wall, at its elevations' mean
    delay; the volume in front of the walls scatters the field back too (:func:`_reverb_volume`). With
    :data:`REVERB_SPREAD` each leg's and each view's delay also spreads as its elevations' do (a Gaussian of their
    variance, :func:`_blur`: a leg's from :func:`_wall_band_var`, a view's from the weights in ``ret``). Contacts
    frustrate the beam's light before it reaches the walls; the wall-to-wall legs only with :data:`REVERB_LEGS`. Solved on a grid of at most ``REVERB_NODES`` nodes, then shared out on the
    model's."""
    p, geom, fine = ctx.params, ctx.geom, ctx.nodes
    L = geom.ray_length  # (S, Z, A)
    S, Z, A = L.shape
    K_fine = fine.t.shape[0]
    step = max(1, K_fine // int(REVERB_NODES))
    while K_fine % step:
        step -= 1
    K = K_fine // step  # the coarse grid: every step-th node's span
    nodes = Nodes(t=(jnp.arange(K, dtype=fine.t.dtype) + 0.5) * (fine.h * step), h=fine.h * step, r=None, dr=None,
                  c1=fine.c1)
    if not REVERB_PADDING >= 1.0:
        raise ValueError(f"guided.REVERB_PADDING must be at least 1 (windows), got {REVERB_PADDING!r}")
    n = 2 * int(round(REVERB_PADDING * K / 2))  # periodic, zero-padded: light wraps after REVERB_PADDING windows
    M = gg.seg_len.shape[0]
    mu_t = p.mu_s_per_m + p.mu_a_per_m
    cg = launch_band(p.n1, gg.fov)[0]  # the guided band's edge
    R = p.end_reflectance
    G, inv_c = _wall_band(el)  # guided share of a Lambertian wall's emission, its mean 1 / cos
    P1 = jnp.where(L > 0, _beam_at_wall(gg, el, L, mu_t), 0.0)  # (S, Z, A)
    Pw = P1 if frus is None else P1 * jnp.prod(1.0 - frus[0], axis=-1)
    t_out = p.emission_time_s + L / (el.c_out * nodes.c1)
    # the beam's light scattered into the guided band on its way out (share cg of the scattered, isotropic): on the
    # walls where the geometry sends it, or evenly when the beam reaches its wall
    path = L / el.c_out
    y = mu_t * path
    y_safe = jnp.where(y > 1e-6, y, 1.0)
    share = jnp.where(y > 1e-6, -jnp.expm1(-y_safe) / y_safe, 1.0 - 0.5 * y)  # (1 - e^-y) / y, finite at y = 0
    scat = gg.dphi[None, :, None] / gg.fov * cg * p.mu_s_per_m * path * share
    # transforms: the beam's arrival at each ray's wall (t_out) and each leg's delay, spread like a deposit
    pr, pi_ = _shifts(t_out / nodes.h - 0.5, n)  # (S, Z, A, F)
    scat = jnp.where(L > 0, scat, 0.0)  # (S, Z, A): none from a ray that leaves the guide at once
    if REVERB_SCATTER_SHARE and gg.hs_share is not None:  # where and when the geometry sends it
        pw = jnp.einsum("sza,szam->sm", scat, gg.hs_share)[..., None]  # (S, M, 1)
        t_hit = p.emission_time_s + (gg.hs_x / el.c_out + gg.hs_r * _band_inv_cos(cg)) / nodes.c1
        qr, qi = _shifts(t_hit / nodes.h - 0.5, n)  # (S, M, F)
        hsr, hsi = qr * pw, qi * pw
    else:
        sw = scat[..., None]
        frac = (gg.seg_len / gg.perimeter_m)[None, :, None]
        hsr = jnp.sum(pr * sw, axis=(1, 2))[:, None, :] * frac  # (S, M, F): evenly on the walls
        hsi = jnp.sum(pi_ * sw, axis=(1, 2))[:, None, :] * frac
    # the power the beam brings each segment (its rays' sum)
    onehot = jax.nn.one_hot(gg.ray_seg, M, dtype=L.dtype)  # (S, Z, A, M)
    h1r = jnp.einsum("szaf,sza,szam->fsm", pr, Pw, onehot)  # (F, S, M)
    h1i = jnp.einsum("szaf,sza,szam->fsm", pi_, Pw, onehot)
    # transfer per frequency
    mu_eff = p.mu_a_per_m + p.mu_s_per_m * (1.0 - cg)
    F = G * gg.seg_view * jnp.exp(-mu_eff * gg.seg_r * inv_c)  # (M, M) k -> l
    dr, di = _shifts(gg.seg_r * inv_c / (nodes.c1 * nodes.h), n)  # (k, l, F)
    dec = bool(REVERB_SPREAD and REVERB_DECONVOLVE)  # the grid's own spread taken back out (nodes squared)
    if REVERB_SPREAD:  # each leg's delay spread over the band's elevations (less its own spline's spread)
        v = _wall_band_var(el) * (gg.seg_r / (nodes.c1 * nodes.h)) ** 2
        b = _blur(jnp.maximum(v - _spline_var, 0.0) if dec else v, n)  # never sharper than its delay: no ringing
        dr, di = dr * b, di * b
    if REVERB_LEGS and frus is not None:
        F = F * _field_leg_transmission(ctx, gg, el)
    RF = (R * F).T[None]  # (1, l, k): H_next[l] = sum_k T[k, l] H[k]
    Tr, Ti = RF * jnp.moveaxis(dr, -1, 0).swapaxes(1, 2), RF * jnp.moveaxis(di, -1, 0).swapaxes(1, 2)  # (F, l, k)
    mv = "flk,fsk->fsl"
    h2r, h2i = _cmv(Tr, Ti, h1r, h1i, mv)
    if EDGE_SCATTER and gg.sc_w is not None:  # the scattered light's first wall hit is _edge_scatter's: here its second on
        xr, xi = _cmv(Tr, Ti, h2r + jnp.moveaxis(hsr, -1, 0), h2i + jnp.moveaxis(hsi, -1, 0), mv)
    else:
        xr, xi = _cmv(Tr, Ti, h2r, h2i, mv)
        xr, xi = xr + jnp.moveaxis(hsr, -1, 0), xi + jnp.moveaxis(hsi, -1, 0)  # the third bounce's irradiance
    # the fourth and fifth bounces
    ar, ai = _cmv(Tr, Ti, xr, xi, mv)
    br, bi = _cmv(Tr, Ti, ar, ai, mv)
    if REVERB_EXACT_ORDERS:  # the later ones summed one by one (a reference for the tests; a loop, not unrolled)
        def order(_, c):
            tr, ti, br, bi = c
            tr, ti = _cmv(Tr, Ti, tr, ti, mv)
            return tr, ti, br + tr, bi + ti

        _, _, br, bi = jax.lax.fori_loop(0, int(REVERB_EXACT_ORDERS), order, (br, bi, br, bi))
    else:
        br, bi = _geometric_tail(ar, ai, br, bi)
    xr, xi = xr + ar + br, xi + ai + bi
    # seen through each ray's first-bounce return, per metre of its segment
    seg = _ray_segment(jnp, L, gg.dphi, gg.cos_wall) / gg.seg_len[gg.ray_seg]  # (S, Z, A)
    # one return per ray at its elevations' mean delay (the field is smooth on the band's spread of delays)
    w = jnp.sum(ret, axis=-1)
    w_safe = jnp.where(w > 0, w, 1.0)
    lag = L / nodes.c1 * jnp.sum(ret / el.c, axis=-1) / w_safe
    kr, ki = _shifts(lag / nodes.h, n)  # (S, Z, A, F)
    if REVERB_SPREAD:  # the view's delay spread over the return elevations (their weights in ret), less the view's
        m2 = (L / nodes.c1) ** 2 * jnp.sum(ret / el.c**2, axis=-1) / w_safe  # and the light's arrival's splines
        v = jnp.maximum(m2 - lag**2, 0.0) / nodes.h**2
        b = _blur(jnp.maximum(v - 2.0 * _spline_var, 0.0) if dec else v, n)
        kr, ki = kr * b, ki * b
    ws = (w * seg)[..., None]
    sidx = np.arange(S)[:, None, None]
    gr, gi = jnp.moveaxis(xr, 0, -1)[sidx, gg.ray_seg], jnp.moveaxis(xi, 0, -1)[sidx, gg.ray_seg]  # (S, Z, A, F)
    out = jnp.sum(ws * (kr * gr - ki * gi), axis=2) + 1j * jnp.sum(ws * (kr * gi + ki * gr), axis=2)  # (S, Z, F)
    # the field's light scattered towards the sensor inside its zone (``mu_s pi q / cbar`` per unit area from
    # an in-plane isotropic field whose walls receive q per metre; isotropic, 1 / (4 pi) per steradian; over
    # each ray's wedge r dphi dr the 1 / r falloff cancels), from the third bounce on, the walls' mean. (The second
    # bounce's light is still on its way from the lit footprint: what of it a ray's volume scatters back arrives
    # with the first return, not a range's delay after it; with it here the tail after the return came out 10-30%
    # above the Monte Carlo's and the 64x calibration's mu_s + mu_a 22% high, against 3% low without.)
    vol = _reverb_volume(p, gg, el, nodes, L)  # (S, Z, K) per unit irradiance per metre
    qbar = (jnp.sum(xr, axis=-1) + 1j * jnp.sum(xi, axis=-1)) / gg.perimeter_m  # (F, S)
    vf = jnp.fft.rfft(vol, n)
    if REVERB_VOLUME_LEAD:  # the light inside reaches the walls a mean forward distance later
        lr, li = _shifts(-gg.forward_m / (_mean_cos(el) * nodes.c1 * nodes.h), n)
        vf = vf * (lr + 1j * li)
    if dec:  # the light's arrival's spline and the lead's
        vf = vf * _blur(jnp.asarray(-(2.0 if REVERB_VOLUME_LEAD else 1.0) * _spline_var, vol.dtype), n)
    out = out + vf * jnp.moveaxis(qbar, 0, -1)[:, None, :]
    # back in time (clipped at 0 against rounding), each coarse node's mass shared by the fine nodes it spans and
    # then a box as wide, centred (linear between the coarse nodes: mass and mean delay kept, never negative; a box
    # of an even width is the mean of two, half a node either side: one alone moved the field half a fine node early)
    if dec:  # the box below spreads by (1 - 1 / step^2) / 6 coarse nodes squared beyond one fine spline (step 1:
        # no box; the fine spline every deposit of the model has, put back)
        out = out * _blur(jnp.asarray(-(1.0 - 1.0 / step**2) / 6.0 if step > 1 else _spline_var, vol.dtype), n)
    coarse = jnp.maximum(jnp.fft.irfft(out, n)[..., :K], 0.0)
    rep = jnp.repeat(coarse / step, step, axis=-1)
    if step == 1:
        return rep
    c = jnp.cumsum(jnp.pad(rep, [(0, 0)] * (rep.ndim - 1) + [(step, step)]), axis=-1)
    a = step // 2
    idx = jnp.arange(K_fine) + step
    box = (c[..., idx + a] - c[..., idx + a - step]) / step  # the fine nodes i - a + 1 .. i + a
    if step % 2:
        return box
    return 0.5 * (box + (c[..., idx + a - 1] - c[..., idx + a - 1 - step]) / step)  # and i - a .. i + a - 1


def _reverb_volume(p, gg, el, nodes, L):
    """Counts per unit wall irradiance (per metre) of the reverberant field scattered towards the sensor along
    each zone's rays, by delay (S, Z, K): ``mu_s dphi cos_s / (4 h cbar) exp(-mu_t c1 t) c1 h sum_j dmu_j c_j``
    over the elevations whose return from the ray's range ``t c_j c1`` is still inside the guide."""
    S, Z, A = L.shape
    cbar = _mean_cos(el)
    mu_t = p.mu_s_per_m + p.mu_a_per_m
    w = (gg.dphi[None, :, None] * gg.cos_sensor)[..., None] * (el.dmu * el.c)  # (S, Z, A, J)
    end = L[..., None] / (el.c * nodes.c1) + 0.5 * nodes.h  # the lag each elevation's return leaves the guide
    ended = _weighted_step(end.reshape(S, Z, -1), w.reshape(S, Z, -1), nodes)  # (S, Z, K)
    cover = jnp.maximum(jnp.sum(w, axis=(2, 3))[..., None] - ended, 0.0)
    lag = nodes.t - 0.5 * nodes.h
    # node k holds the lags within half a node of k h; the first only the half after 0 (the trapezoid rule: without
    # it the field's mass and mean delay carried an error of first order in the node spacing, see _reverb)
    half = jnp.where(jnp.arange(lag.shape[0]) == 0, 0.5, 1.0).astype(lag.dtype)
    return ((p.mu_s_per_m / (4.0 * gg.thickness_m * cbar) * nodes.c1 * nodes.h) * half * cover
            * jnp.exp(-mu_t * nodes.c1 * lag))


def _leg_frame(p, src, d):
    """Each contact against legs from ``src`` along ``d`` (``src`` broadcast like ``d``, (..., 2)): the legs'
    lengths (...) and unit directions (..., 2), the contacts' distances along and across them (..., N)."""
    length = jnp.sqrt(jnp.sum(d**2, -1) + 1e-30)  # in-plane
    u = d / length[..., None]
    rel = p.touch_xy_m - src[..., None, :]  # (..., N, 2)
    along = jnp.sum(rel * u[..., None, :], -1)
    across = rel[..., 0] * u[..., None, 1] - rel[..., 1] * u[..., None, 0]
    return length, u, along, across


def _wall_light_frustrated(p, gg, el, chord):
    """Share of a Lambertian wall's guided light frustrated over ``chord`` (..., N) of each contact: its top-face
    hits per guided elevation (``chord |mu| / (2 h cos)``), averaged over the band with the wall's guided weights
    (``dmu cos``)."""
    P = _lost_back(p, gg, el, chord, _coupling(gg.skin, p.touch_strength))  # (..., N, J)
    w = el.dmu * el.c / jnp.sum(el.dmu * el.c)  # a Lambertian wall's guided emission per elevation
    return jnp.sum(P * w, -1)


def _leg_transmission(ctx, gg, el, src, d):
    """Share of the wall-to-wall light of :func:`_edge_second` (from ``src`` (S, I, 2) along ``d``
    (S, Z, A, I, 2) to the receiving wall point) that crosses every contact unfrustrated: each
    contact's chord of the leg (:func:`_wall_light_frustrated`), the product over the contacts; a
    contact beyond either end of the leg does nothing (a smooth step one radius wide)."""
    p = ctx.params
    rad = p.touch_radius_m  # (N,)
    length, _, along, across = _leg_frame(p, src[:, None, None], d)  # (S, Z, A, I), (S, Z, A, I, N)
    chord = _disk_chord(rad, across)
    inside = jax.nn.sigmoid(along / rad) * jax.nn.sigmoid((length[..., None] - along) / rad)
    return jnp.prod(1.0 - _wall_light_frustrated(p, gg, el, chord) * inside, axis=-1)  # (S, Z, A, I)


def _contacts_between(ctx, gg, el):
    """Transmission (S, N, J) of each contact's light through the other contacts between it and each sensor:
    out at the launched beam's elevation and back at each return elevation, each other contact frustrating
    its chord along the line (like :func:`_frustration`). The line is taken to the points across the contact's
    disk (``CONTACT_LINES`` of them, Chebyshev-weighted like the disk's chords): a contact half hidden behind
    another is half shadowed. Behind one contact 6 cm ahead of OptoSkin's S4 a second 4 cm further on returns
    17% less light in the Monte Carlo, 21% less in the model, 3.5% more without this (the shadows' overlap;
    experiments/contact_behind_contact_mc.py)."""
    p, cg = ctx.params, ctx.contacts
    d = p.touch_xy_m[None, :, :] - ctx.geom.sensor_xy[:, None, :]  # (S, N, 2)
    D = jnp.maximum(cg.distance, 1e-6)  # (S, N)
    ux, uy = d[..., 0] / D, d[..., 1] / D  # (S, N) towards each target contact
    # the blockers (index m) in each target's (index n) frame: along and across the line to its centre
    along = d[:, None, :, 0] * ux[..., None] + d[:, None, :, 1] * uy[..., None]  # (S, Nt, Nb)
    across = -d[:, None, :, 0] * uy[..., None] + d[:, None, :, 1] * ux[..., None]
    k = jnp.arange(1, CONTACT_LINES + 1, dtype=D.dtype)
    u = jnp.cos(k * math.pi / (CONTACT_LINES + 1))  # lines to points across the target's disk
    wk = jnp.sin(k * math.pi / (CONTACT_LINES + 1)) ** 2
    wk = wk / jnp.sum(wk)
    rad = p.touch_radius_m
    off = across[..., None] - u * (rad[None, :, None] / D[..., None])[..., None] * along[..., None]  # (S, Nt, Nb, K)
    other = 1.0 - jnp.eye(p.n_touches, dtype=D.dtype)
    before = jax.nn.sigmoid((D[..., None] - along) / rad[None, None, :]) * other  # blocker before the target
    chord = jnp.where(along[..., None] > 0, _disk_chord(rad[None, None, :, None], off), 0.0) * before[..., None]
    fc = _coupling(gg.skin, p.touch_strength)[None, None, :, None]  # the blocker's coupling
    T_out = 1.0 - _lost_out(p, gg, el, chord, fc)
    T_ret = 1.0 - _lost_back(p, gg, el, chord, fc)  # (S, Nt, Nb, K, J)
    T = jnp.sum(wk[:, None] * T_out[..., None] * T_ret, axis=-2)  # (S, Nt, Nb, J)
    return jnp.prod(T, axis=2)


def _touch(ctx, gg, el):
    """Light the skin returns: the share of each contact's light frustrated into the skin (its area over
    ``D``, the hits per metre of chord) times the albedo, Lambertian from the face (``|mu| / pi`` per
    steradian), back over the in-plane angle ``a cos / D``; spread over the disk's range like the default
    touch, and shared among the zones by the contact's area in each zone's wedge (times depend on the
    sensor, contact, range sample and elevation only, so they are deposited once per sensor)."""
    from .components import contact_ranges

    p, nodes, cg = ctx.params, ctx.nodes, ctx.contacts
    skin = gg.skin
    rad = p.touch_radius_m
    D, w = contact_ranges(ctx, floor=0.5 * rad[:, None])  # (S, N, M), (M,)
    mu_t = p.mu_s_per_m + p.mu_a_per_m
    fc = _coupling(skin, p.touch_strength)  # (N,)
    chord = 0.5 * math.pi * rad  # mean chord of a disk seen from afar
    P_out = _lost_out(p, gg, el, chord, fc)  # (N,)
    P_ret = _lost_back(p, gg, el, chord, fc)  # (N, J)
    albedo = skin.diffuse_albedo_jax(p.n1)
    width = 2.0 * jnp.arctan(rad / cg.distance)  # (S, N) the contact's angular width
    ncos = gg.sensor_normal  # (S, 2)
    d = p.touch_xy_m[None] - ctx.geom.sensor_xy[:, None]  # (S, N, 2)
    cos_s = jnp.clip(jnp.sum(d * ncos[:, None], -1) / cg.distance, 0.0, 1.0)  # (S, N)
    # frustrated share of the light sent towards the contact: (its angular width / fov) P_out
    base = (width * cos_s / gg.fov)[..., None] * P_out[None, :, None] * albedo * w / (math.pi * gg.thickness_m * D)
    base = base * jnp.exp(-mu_t * D / el.c_out)  # (S, N, M)
    # the return crosses, on average, half its own contact's chord. The skin lies on the top face: its
    # Lambertian return enters the guide going down only, one sign of the band (``dmu`` weighs both
    # signs, as for the far edge, a wall that sends light up and down): half of ``dmu``. With both
    # signs the first-order return was 2.2x the Monte Carlo's (one contact, absorbing edges, 0.01 /m
    # scattering: experiments/eval_mc_data.py, first_order_touch); now 0.9-1.0x.
    amp = base[..., None] * (0.5 * el.dmu) * el.mu * jnp.exp(-mu_t * D[..., None] / el.c)
    amp = amp * (1.0 - 0.5 * P_ret[None, :, None, :])
    if CONTACT_SHADOW and ctx.shadowing and p.n_touches > 1:
        amp = amp * _contacts_between(ctx, gg, el)[:, :, None, :]
    t = p.emission_time_s + D[..., None] * (1.0 / el.c_out + 1.0 / el.c) / nodes.c1  # (S, N, M, J)
    S, N = amp.shape[:2]
    per_contact = deposit(t.reshape(S, N, -1), amp.reshape(S, N, -1), nodes)  # (S, N, K)
    return p.gain[:, None, None] * jnp.einsum("szn,snk->szk", cg.fraction, per_contact)


def _touch_diffuse(ctx, gg, el):
    """Second order: light the diffuse far edges send across a contact, frustrated into the skin and
    returned. Each ray's wall point is a Lambertian source (``R cos / pi``); the contact's area over
    its distance ``rho`` from it times ``|mu| / (2 h cos)`` hits per metre gives the frustrated share;
    the skin returns it to the sensor like the first-order touch (times at the band's mean delay
    on the middle leg). With :data:`SECOND_ORDER_RECIPROCAL` also each path's reverse (the
    contact's return lighting the wall point, which returns it to the sensor): by reciprocity the
    same amplitude and delay, detected in the wall point's zone."""
    p, geom, nodes, cg = ctx.params, ctx.geom, ctx.nodes, ctx.contacts
    skin = gg.skin
    L = geom.ray_length  # (S, Z, A)
    mu_t = p.mu_s_per_m + p.mu_a_per_m
    wall = geom.sensor_xy[:, None, None, :] + L[..., None] * jnp.stack([jnp.cos(geom.ray_angle), jnp.sin(geom.ray_angle)], -1)
    to_c = p.touch_xy_m[None, None, None, :, :] - wall[..., None, :]  # (S, Z, A, N, 2)
    rho = jnp.sqrt(jnp.sum(to_c**2, -1) + p.touch_radius_m**2)  # (S, Z, A, N), never 0
    cos_w = jnp.clip(jnp.sum(to_c * gg.wall_normal[..., None, :], -1) / rho, 0.0, 1.0)
    fc = _coupling(skin, p.touch_strength)  # (N,)
    Rs = _fresnel(p.n1, skin.n, el.mu)  # (J,)
    # frustrated share per unit power leaving the wall point, summed over the band
    band = jnp.sum(el.dmu * el.mu * (1.0 - Rs) * jnp.exp(-mu_t * rho[..., None] / el.c), -1)  # (S, Z, A, N)
    frus = p.end_reflectance * cos_w * p.touch_radius_m**2 / (2.0 * gg.thickness_m * rho) * fc * band
    reach = jnp.where(L > 0, _beam_at_wall(gg, el, L, mu_t), 0.0)  # (S, Z, A)
    src = reach[..., None] * frus * skin.diffuse_albedo_jax(p.n1)  # (S, Z, A, N)
    # back to the sensor from the contact (distance D, Lambertian from the face)
    D = jnp.maximum(cg.distance, p.touch_radius_m)  # (S, N)
    d = p.touch_xy_m[None] - geom.sensor_xy[:, None]
    cos_s = jnp.clip(jnp.sum(d * gg.sensor_normal[:, None], -1) / cg.distance, 0.0, 1.0)  # (S, N)
    back = 0.5 * el.dmu * el.mu * jnp.exp(-mu_t * D[..., None] / el.c) * (cos_s / (math.pi * gg.thickness_m * D))[..., None]
    amp = src[..., None] * back[:, None, None]  # (S, Z, A, N, J)
    inv_c = jnp.sum(el.dmu * el.mu / el.c) / jnp.sum(el.dmu * el.mu)  # mean 1/cos of a Lambertian source
    t = p.emission_time_s + (L[..., None, None] / el.c_out + rho[..., None] * inv_c + D[:, None, None, :, None] / el.c) / nodes.c1
    S, Z, N = amp.shape[0], amp.shape[1], amp.shape[3]
    t = jnp.broadcast_to(t, src.shape + el.c.shape)  # (S, Z, A, N, J)
    per_contact = deposit(jnp.moveaxis(t, 3, 1).reshape(S, N, -1), jnp.moveaxis(amp, 3, 1).reshape(S, N, -1), nodes)  # (S, N, K)
    out = jnp.einsum("szn,snk->szk", cg.fraction, per_contact)
    if SECOND_ORDER_RECIPROCAL:
        # the reversed paths: same amplitudes and delays, detected in the wall point's zone
        out = out + deposit(t.reshape(S, Z, -1), amp.reshape(S, Z, -1), nodes)
    return p.gain[:, None, None] * out


def _touch_free(ctx, gg, el):
    """Without a skin model: the free touch strength (counts as the default optics' at 1 m), guided timing."""
    from .components import contact_ranges, falloff, shadow

    p, nodes, cg = ctx.params, ctx.nodes, ctx.contacts
    r, w = contact_ranges(ctx)  # (S, N, M), (M,)
    mu_t = p.mu_s_per_m + p.mu_a_per_m
    beta = p.touch_strength * cg.fraction  # (S, Z, N)
    fall = falloff(r, p.near_field_m)
    att = jnp.exp(-mu_t * r[..., None] * (1.0 / el.c_out + 1.0 / el.c))  # (S, N, M, J)
    ew = el.dmu * el.mu / jnp.sum(el.dmu * el.mu)  # Lambertian return over the band
    amp = beta[..., None, None] * (w[:, None] * fall[..., None] * att * ew)[:, None]  # (S, Z, N, M, J)
    if ctx.shadowing:
        sh = shadow(jnp.broadcast_to(r[:, None], amp.shape[:-1]), cg, p, exclude_self=True)
        amp = amp * sh[..., None]
    t = p.emission_time_s + r[..., None] * (1.0 / el.c_out + 1.0 / el.c) / nodes.c1
    S, Z = amp.shape[:2]
    t = jnp.broadcast_to(t[:, None], amp.shape).reshape(S, Z, -1)
    return p.gain[:, None, None] * deposit(t, amp.reshape(S, Z, -1), nodes)


def _subrays(rel, zone_lo, zone_hi):
    """Angles (Z, A, NF_SUBRAYS) evenly across each ray's interval of ``rel`` (Z, A) within its zone."""
    A = rel.shape[1]
    dphi = (np.asarray(zone_hi) - np.asarray(zone_lo))[:, None, None] / A
    return rel[..., None] + dphi * ((np.arange(NF_SUBRAYS) + 0.5) / NF_SUBRAYS - 0.5)


def _near_field_table(rel, zone_lo, zone_hi, psi, w_ray, aperture_m: float) -> dict:
    """The distributed terms' near field from the aperture (:data:`NEAR_FIELD_APERTURE`), NumPy, at build time.

    A zone is a condition on the angle of arrival. Light from a point at range ``r`` on a ray reaches the aperture
    (``a`` wide along the edge) over the arrival angles of the lines from the aperture's points to it: exactly,
    from ``atan2(r sin(psi) -+ a/2, r cos(psi))`` (``psi`` the ray's angle from the edge's normal), about
    ``ray +- (a/2) cos(psi) / r`` once ``r >> a``. Near the sensor a ray's light therefore spreads over the
    neighbouring zones and, at the fan's two ends, out of it. ``f_sz(r)``: every ray's share of those angles in zone
    ``z`` of sensor ``s`` over ``a``, weighted by the rays' ``w_ray`` ((S, Z, A) or (Z,)) and averaged across each
    ray's interval of angles (:data:`NF_SUBRAYS`); far from the sensor it is ``W_sz / r``, ``W_sz`` the zone's own
    rays' ``w cos(psi)``.
    Its integral from 0, ``Phi_sz(r)``, is tabulated as ``Psi = Phi - W log r`` (which levels off) on
    :data:`NF_POINTS` ranges uniform in log r (trapezoids in log r, exact for ``1/r``), with ``Phi`` at the first
    (where ``f`` is constant: every ray's angles cover the fan). ``rel`` (Z, A): the rays' angles from the sensor's
    axis; ``psi`` (S, Z, A)."""
    lnr = np.linspace(math.log(NF_R_MIN), math.log(NF_R_MAX), NF_POINTS)
    r = np.exp(lnr)
    off = _subrays(rel, zone_lo, zone_hi) - rel[..., None]  # (Z, A, U): across each ray's interval
    b = 0.5 * aperture_m
    lo_k, hi_k = np.asarray(zone_lo, float), np.asarray(zone_hi, float)
    psi = np.asarray(psi, float)
    w_ray = np.asarray(w_ray, float)
    w_ray = np.broadcast_to(w_ray[None, :, None] if w_ray.ndim == 1 else w_ray, psi.shape)
    f = np.zeros((psi.shape[0], len(lo_k), NF_POINTS))
    for u in range(off.shape[-1]):
        ps = (psi + off[None, ..., u])[..., None]  # (S, Z, A, 1)
        x, y = r * np.sin(ps), r * np.cos(ps)
        d1, d2 = np.arctan2(x - b, y) - ps, np.arctan2(x + b, y) - ps  # (S, Z, A, N)
        ra = (rel + off[..., u])[None, :, :, None]
        lo_a, hi_a = ra + np.minimum(d1, d2), ra + np.maximum(d1, d2)
        for k in range(len(lo_k)):
            ov = np.clip(np.minimum(hi_k[k], hi_a) - np.maximum(lo_k[k], lo_a), 0.0, None)  # (S, Z, A, N)
            f[:, k] += np.einsum("szan,sza->sn", ov, w_ray) / (aperture_m * off.shape[-1])
    fr = f * r  # the integrand in log r
    phi = f[..., :1] * r[0] + np.concatenate(
        [np.zeros_like(fr[..., :1]), np.cumsum(0.5 * (fr[..., 1:] + fr[..., :-1]) * np.diff(lnr), -1)], -1)
    w = np.einsum("sza,sza->sz", np.clip(np.cos(psi), 0.0, None), w_ray)
    tab = np.moveaxis(phi - w[..., None] * lnr, -1, 0)  # (N, S, Z)
    return {"nf_w": w, "nf_tab": np.stack([tab[:-1], np.diff(tab, axis=0)], -1), "nf_phi0": phi[..., 0]}


def _edge_mixing(rel, zone_lo, zone_hi, cos_sensor, aperture_m: float, ray_length) -> np.ndarray:
    """How the far edge's first returns are shared among the zones (:data:`EDGE_APERTURE`), NumPy at build time:
    a wall point at ``L`` on a ray reaches the aperture over arrival angles ``ray +- b cos(psi) / L`` (``b`` half the
    aperture); the share of that interval (averaged across the ray's interval of angles) inside a zone is the share
    of the return the zone sees. Zone ``k`` takes its own rays and the :data:`EDGE_APERTURE_RAYS` nearest of each
    neighbour, a neighbour's at the time of zone ``k``'s own ray next to them (adjacent rays' walls lie within
    ``L dphi tan(psi_wall)`` of each other: a few picoseconds). Returns the mix (S, Z, A, Z * A): zone ``k``'s
    ray ``a`` takes ``mix[s, k, a] @ returns[s].reshape(Z * A)``."""
    S, Z, A = np.shape(cos_sensor)
    nb = min(int(EDGE_APERTURE_RAYS), A)
    half = 0.5 * aperture_m * np.asarray(cos_sensor, float) / np.maximum(np.asarray(ray_length, float), 1e-9)  # (S, Z, A)
    half = np.maximum(half, 1e-15)[..., None]
    sub = _subrays(rel, zone_lo, zone_hi)[None]  # (1, Z, A, U)
    mix = np.zeros((S, Z, A, Z * A))
    for k in range(Z):
        lo, hi = zone_lo[k], zone_hi[k]
        share = np.mean(np.clip(np.minimum(hi, sub + half) - np.maximum(lo, sub - half), 0.0, None) / (2.0 * half), -1)
        for a in range(A):  # the own rays
            mix[:, k, a, k * A + a] = share[:, k, a]
        for j in range(nb):  # the neighbours' nearest rays, at the own edge rays' times
            if k > 0:
                mix[:, k, 0, (k - 1) * A + A - 1 - j] = share[:, k - 1, A - 1 - j]
            if k < Z - 1:
                mix[:, k, A - 1, (k + 1) * A + j] = share[:, k + 1, j]
    return mix


def _scatter_tables(lx: float, ly: float, thickness: float, xy, ang, L, cos_wall, cos_sensor, dphi, fov: float,
                    n1: float) -> dict:
    """Static geometry of :func:`_edge_scatter` (NumPy): per sensor, zone and term (0: the beam's light scattered on
    to the lit walls; 1: the lit walls' light scattered back by the volume) a kernel on :data:`SCATTER_BINS` bins of
    path difference from the zone's first return (``SCATTER_BIN_M`` wide from ``SCATTER_MIN_M``), each bin's weight
    (pure geometry, relative to the zone's first return) and its mean lengths: ``A`` (the beam's leg less the direct
    one's), ``B`` (the diffuse leg from the scattering point to the wall, or from the wall to the scattering point) and
    ``C`` (the view's leg less the direct return's). The bins are laid out with the in-plane speeds at ``n1`` (the
    scene's); the model takes each bin's delay and attenuation from its mean lengths at the fitted ``n1``. With
    :data:`SCATTER_OWN_RETURN` each entry's delay is counted from its own element's (term 0) or ray's (term 1) return
    less the zone's mean first return (``A`` carries the difference), and term 0's weights are relative to the zone's
    first return, each element's light returned with its own ``cos cos / L``. Term 1's view leg travels at the band's
    ``1 / cos`` and the direct return at a Lambertian wall's: ``A`` also carries that difference's ``(g_iso - g_wall)
    L``. Term 1's leg from the wall into the volume is binned at ``g_iso`` with :data:`SCATTER_FLUENCE` (``g_wall``
    without); with :data:`SCATTER_SPREAD` each entry is binned at that many elevations of its diffuse leg, ``B``
    carrying each one's ``1 / cos`` relative to the band's mean.

    Term 0: the beam (share ``dphi / fov`` per ray) at ``SCATTER_SOURCES`` points along each ray; a wall element
    ``l`` at distance ``rho`` takes ``l cos / (2 pi rho)`` of a point's in-plane isotropic light; the zone's rays'
    elements (``SCATTER_ELEMENTS`` per ray's footprint) return it as the beam's own light there. Relative to the
    zone's beam power on its walls. Term 1: each ray's footprint elements re-emit their beam power (Lambertian in the
    plane, ``cos / 2`` per radian: fluence ``cos / (2 rho)``, ``1 / pi`` of it the wall-irradiance equivalent of
    :func:`_reverb_volume`) and the volume at ``SCATTER_SOURCES`` ranges along each of the zone's rays scatters it
    back (``dphi cos_s dr / (4 h)`` per unit irradiance per metre); relative to the zone's first return per unit
    reflectance (``sum dphi / fov cos_wall cos_s / (pi h L)``)."""
    S, Z, A = ang.shape
    cg, _, c_out = (float(v) for v in launch_band(float(n1), fov))
    g_iso = float(_band_inv_cos(cg))
    g_wall = cg / (0.5 * (math.asin(cg) + cg * math.sqrt(1.0 - cg * cg)))  # a Lambertian wall's flux-weighted 1 / cos
    NK, NS, NE = int(SCATTER_BINS), int(SCATTER_SOURCES), int(SCATTER_ELEMENTS)
    names = _scatter_terms()
    out = {k: np.zeros((S, Z, len(names), NK)) for k in ("w", "a", "b", "c")}
    u_leg, p_leg = _leg_spread(cg, int(SCATTER_SPREAD))  # the diffuse legs' 1 / cos over the band, relative to its mean
    g_back = g_iso if SCATTER_FLUENCE else g_wall  # a wall-to-volume leg (terms 1 and 2), as _edge_scatter times it
    if SCATTER_REDIRECT:  # term 2's scattering points: the centres of a grid over the guide
        nx, ny = max(1, round(lx / SCATTER_GRID_M)), max(1, round(ly / SCATTER_GRID_M))
        gx, gy = np.meshgrid((np.arange(nx) + 0.5) * lx / nx, (np.arange(ny) + 0.5) * ly / ny, indexing="ij")
        Q, dA = np.stack([gx.ravel(), gy.ravel()], -1), lx * ly / (nx * ny)
    zone_power = np.asarray(dphi, float) * A / fov  # (Z,) the beam's share on each zone's walls
    for s in range(S):
        s0 = np.asarray(xy[s], float)
        a_s, L_s = np.asarray(ang[s], float), np.asarray(L[s], float)  # (Z, A)
        # footprint elements of every ray: positions, lengths, inward normals, distances
        off = ((np.arange(NE) + 0.5) / NE - 0.5)[None, None, :] * np.asarray(dphi, float)[:, None, None]
        th = a_s[..., None] + off  # (Z, A, NE)
        c, sn = np.cos(th), np.sin(th)
        tx, ty = _to_walls(lx, ly, s0[0], s0[1], c, sn)
        t = np.clip(np.minimum(tx, ty), 0.0, None)
        cw, nrm = _wall_hit(tx, ty, c, sn)
        W = s0 + t[..., None] * np.stack([c, sn], -1)  # (Z, A, NE, 2)
        ell = t * (np.asarray(dphi, float)[:, None, None] / NE) / np.maximum(cw, 0.05)
        live = np.broadcast_to(L_s[..., None] > 0, t.shape)
        # points along every ray (midpoints)
        u = (np.arange(NS) + 0.5) / NS
        x = L_s[..., None] * u  # (Z, A, NS)
        P = s0 + x[..., None] * np.stack([np.cos(a_s), np.sin(a_s)], -1)[..., None, :]  # (Z, A, NS, 2)
        dx = np.broadcast_to((L_s / NS)[..., None], x.shape)
        zone_e = np.broadcast_to(np.arange(Z)[:, None, None], t.shape).ravel()
        zone_p = np.broadcast_to(np.arange(Z)[:, None, None], x.shape).ravel()
        # each element's return (per unit power on it) and its delay from its zone's mean first return, as a length
        # of the beam's leg (so that ``A / c_out`` is the delay): the first return weights the zone's elements by
        # their beam share and return (``cos cos / L``, as :func:`_edge`)
        ret = cw * np.asarray(cos_sensor[s], float)[..., None] / np.maximum(t, 1e-9) * live  # (Z, A, NE)
        share = np.asarray(dphi, float)[:, None, None] / fov / NE * live * ret
        ret_z = share.sum((1, 2))  # (Z,)
        t_z = (share * t).sum((1, 2)) / np.maximum(ret_z, 1e-300)
        own = (t - t_z[:, None, None]) * (1.0 + g_wall * c_out)  # (Z, A, NE)
        if not SCATTER_OWN_RETURN:
            ret, own = np.ones_like(ret), np.zeros_like(own)
        # term 0: beam point (sources: every ray) -> element (targets: every ray), binned by the element's zone
        Wf, Pf, nf = W.reshape(-1, 2), P.reshape(-1, 2), nrm.reshape(-1, 2)
        ex, ey = Wf[None, :, 0] - Pf[:, None, 0], Wf[None, :, 1] - Pf[:, None, 1]  # (points, elements)
        rho = np.sqrt(ex * ex + ey * ey + thickness**2)
        cos_in = np.clip(-(ex * nf[None, :, 0] + ey * nf[None, :, 1]) / rho, 0.0, 1.0)
        beam = (np.asarray(dphi, float)[:, None, None] / fov * dx).ravel()  # the beam's share per point times dx
        w0 = beam[:, None] * (ell * live * ret).ravel()[None] * cos_in / (2.0 * np.pi * rho)
        A0 = x.ravel()[:, None] - t.ravel()[None] + own.ravel()[None]
        B0 = np.broadcast_to(rho, w0.shape)
        norm0 = ret_z if SCATTER_OWN_RETURN else zone_power  # the zone's first return, or its power on the walls
        for u, pq in zip(u_leg, p_leg):
            _bin_into(out, s, 0, np.broadcast_to(zone_e[None], w0.shape), A0 / c_out + g_iso * u * B0, w0 * pq, A0,
                      B0 * u, 0.0 * B0, norm0[zone_e][None])
        # term 1: element (sources: every ray) -> volume point on a zone's ray (targets), binned by the point's zone
        rho = rho.T  # (elements, points): from each element to each point
        cos_b = np.clip(-(ex.T * nf[:, None, 0] + ey.T * nf[:, None, 1]) / rho, 0.0, 1.0)
        src = (np.asarray(dphi, float)[:, None, None] / fov / NE * live).ravel()  # beam share per element
        view = (np.asarray(dphi, float)[:, None, None] * np.asarray(cos_sensor[s], float)[..., None] * dx
                / (4.0 * thickness)).ravel()
        w1 = src[:, None] * cos_b / (2.0 * np.pi * rho) * view[None]
        Lp = np.broadcast_to(L_s[..., None], x.shape).ravel()  # the target ray's wall distance
        A1 = np.broadcast_to(L_s[..., None], t.shape).ravel()[:, None] - Lp[None]
        # each ray's first return per unit reflectance (Z, A), and the zone's
        rr = np.asarray(dphi, float)[:, None] / fov * np.asarray(cos_wall[s], float) * np.asarray(cos_sensor[s], float) \
            / (np.pi * thickness * np.maximum(L_s, 1e-9)) * (L_s > 0)
        direct = rr.sum(1)  # (Z,)
        if SCATTER_OWN_RETURN:  # from the zone's mean first return, not the target ray's
            L_z = (rr * L_s).sum(1) / np.maximum(direct, 1e-300)
            A1 = A1 + ((Lp - L_z[zone_p]) * (1.0 + g_wall * c_out))[None]
        # the view's leg travels at the band's 1/cos (isotropic scattering), the direct return it is counted from at
        # a Lambertian wall's: ``C`` carries the difference of lengths at ``g_iso``, ``A`` the rest, ``(g_iso - g_wall)
        # Lp`` (about 3 mm at 30 cm, n1 = 1.4; at the scene's n1, as ``own``)
        A1 = A1 + (Lp * (g_iso - g_wall) * c_out)[None]
        C1 = (x.ravel() - Lp)[None]
        for u, pq in zip(u_leg, p_leg):
            _bin_into(out, s, 1, np.broadcast_to(zone_p[None], w1.shape), A1 / c_out + g_back * u * rho + g_iso * C1,
                      w1 * pq, np.broadcast_to(A1, w1.shape), rho * u, np.broadcast_to(C1, w1.shape), direct[zone_p][None])
        if SCATTER_REDIRECT:
            # term 2: element (source, every ray: its beam power, Lambertian in the plane, cos / 2 per radian) ->
            # grid point q (``cos / (2 rho1)`` per unit area of the in-plane flux it scatters) -> element (target,
            # every ray: ``l cos / (2 pi rho2)`` of q's in-plane isotropic light), binned by the target's zone
            Ls_e = np.broadcast_to(L_s[..., None], t.shape).ravel()  # each element's ray length
            d1 = Q[None] - Wf[:, None]  # (elements, points)
            rho1 = np.sqrt(np.sum(d1 * d1, -1) + thickness**2)
            emit = src[:, None] * np.clip(np.sum(d1 * nf[:, None], -1) / rho1, 0.0, None) / (2.0 * rho1) * dA
            d2 = Wf[None] - Q[:, None]  # (points, elements)
            rho2 = np.sqrt(np.sum(d2 * d2, -1) + thickness**2)
            land = (ell * live * ret).ravel()[None] * np.clip(-np.sum(d2 * nf[None], -1) / rho2, 0.0, None) / (2.0 * np.pi * rho2)
            for i in range(Wf.shape[0]):  # one source element at a time: (points, elements)
                w2 = emit[i][:, None] * land
                if not w2.any():
                    continue
                A2 = np.broadcast_to((Ls_e[i] - Ls_e + own.ravel())[None], w2.shape)
                B2 = np.broadcast_to(rho1[i][:, None], w2.shape)
                _bin_into(out, s, names.index("redirect"), np.broadcast_to(zone_e[None], w2.shape),
                          A2 / c_out + g_back * B2 + g_iso * rho2, w2, A2, B2, rho2, norm0[zone_e][None])
    w = out["w"]
    for key in ("a", "b", "c"):  # the bins' mean lengths
        out[key] = np.where(w > 0, out[key] / np.where(w > 0, w, 1.0), 0.0)
    return out


def _leg_spread(cg: float, n: int) -> tuple:
    """A diffuse leg's ``1 / cos`` over the guided band (uniform in ``mu`` on ``|mu| < cg``) relative to its mean,
    and the weights: ``n`` Gauss-Legendre nodes, scaled so that their weighted mean is 1 (the band's mean ``1 / cos``
    stays the closed form's); ``n = 0``: the mean alone, ``((1.0,), (1.0,))``."""
    if n <= 0:
        return (1.0,), (1.0,)
    x, w = np.polynomial.legendre.leggauss(n)
    x, w = 0.5 * (x + 1.0), 0.5 * w
    u = 1.0 / np.sqrt(1.0 - (cg * x) ** 2)
    return tuple(u / np.sum(w * u)), tuple(w)


def _scatter_terms() -> tuple:
    """The names of :func:`_edge_scatter`'s kernels under the module's switches, in the tables' order."""
    return ("beam_to_walls", "walls_back") + (("redirect",) if SCATTER_REDIRECT else ())


#: The build-time tables (:func:`_scatter_tables`, :func:`_near_field_table`) of the last few geometries: a model is
#: often built many times for one scene (a study's variants, a test file's cases, a calibration's restarts), and the
#: near field's table alone took 0.53 s of a 0.75 s build of the touch-six scene.
_TABLE_CACHE: dict = {}


def _memo(fn, settings: tuple, *args) -> dict:
    """``fn(*args)`` (a dict of NumPy arrays), remembered by its inputs (arrays by shape, dtype and bytes, the rest by
    value) and the module's ``settings`` that ``fn`` reads; copies out, so no caller can change what is kept."""
    key = (fn.__name__, settings) + tuple((a.shape, a.dtype.str, a.tobytes()) if isinstance(a, np.ndarray) else a
                                          for a in args)
    if key not in _TABLE_CACHE:
        if len(_TABLE_CACHE) >= 32:
            _TABLE_CACHE.pop(next(iter(_TABLE_CACHE)))
        _TABLE_CACHE[key] = fn(*args)
    return {k: v.copy() for k, v in _TABLE_CACHE[key].items()}


def _scatter_tables_cached(lx, ly, thickness, xy, ang, L, cos_wall, cos_sensor, dphi, fov, n1) -> dict:
    """:func:`_scatter_tables`, remembered by its inputs and the module's ``SCATTER_*`` settings (:func:`_memo`)."""
    arrays = [np.ascontiguousarray(a, float) for a in (xy, ang, L, cos_wall, cos_sensor, dphi)]
    settings = (SCATTER_BINS, SCATTER_BIN_M, SCATTER_MIN_M, SCATTER_SOURCES, SCATTER_ELEMENTS, SCATTER_REDIRECT,
                SCATTER_GRID_M, SCATTER_OWN_RETURN, SCATTER_SPREAD, SCATTER_FLUENCE)
    return _memo(_scatter_tables, settings, float(lx), float(ly), float(thickness), *arrays, float(fov), float(n1))


def _near_field_table_cached(rel, zone_lo, zone_hi, psi, w_ray, aperture_m: float) -> dict:
    """:func:`_near_field_table`, remembered by its inputs and the module's ``NF_*`` settings (:func:`_memo`)."""
    arrays = [np.ascontiguousarray(a, float) for a in (rel, zone_lo, zone_hi, psi, w_ray)]
    return _memo(_near_field_table, (NF_R_MIN, NF_R_MAX, NF_POINTS, NF_SUBRAYS), *arrays, float(aperture_m))


def _bin_into(out, s, term, zone, delta, w, A, B, C, norm):
    """Add weights ``w`` at path differences ``delta`` into ``out``'s bins of sensor ``s`` and ``term`` (per zone),
    normalised by ``norm``, and the lengths ``A``, ``B``, ``C`` times ``w`` into ``out``'s ``a``, ``b``, ``c`` (the
    caller divides them by the weights once every call is in)."""
    NK = out["w"].shape[-1]
    k = np.floor((delta - SCATTER_MIN_M) / SCATTER_BIN_M).astype(np.int64)
    w = np.where((k >= 0) & (k < NK), w / np.maximum(norm, 1e-300), 0.0)
    k = np.clip(k, 0, NK - 1)
    Z = out["w"].shape[1]
    flat = (np.asarray(zone) * NK + k).ravel()
    out["w"][s, :, term] += np.bincount(flat, weights=w.ravel(), minlength=Z * NK).reshape(Z, NK)
    for key, v in (("a", A), ("b", B), ("c", C)):  # weighted sums here, means at the end (:func:`_scatter_tables`)
        out[key][s, :, term] += np.bincount(flat, weights=(w * v).ravel(), minlength=Z * NK).reshape(Z, NK)


def _near_field(gg: "GuidedGeometry", r_edges):
    """Each zone's light from the ranges between consecutive ``r_edges`` (J, K + 1), ``>= 0``, under the aperture's
    near field (S, Z, J, K): :func:`_near_field_table`'s integral looked up (linear in log r) at the edges and
    differenced (each edge once). The table is laid out by range (``nf_tab``: value and slope per interval), so the
    lookup is one gather of rows."""
    n = gg.nf_tab.shape[0] + 1
    ln0 = math.log(NF_R_MIN)
    step = (math.log(NF_R_MAX) - ln0) / (n - 1)
    ln = jnp.log(jnp.maximum(r_edges, NF_R_MIN))
    u = jnp.clip((ln - ln0) / step, 0.0, n - 1.0)
    i = jnp.minimum(jnp.floor(u).astype(jnp.int32), n - 2)
    f = (u - i)[..., None, None]
    rows = gg.nf_tab[i.reshape(-1)].reshape(*i.shape, *gg.nf_tab.shape[1:])  # (J, K + 1, S, Z, 2)
    phi = gg.nf_w * ln[..., None, None] + rows[..., 0] + f * rows[..., 1]  # Phi(r) from the sensor out
    # below the grid's first range every ray's angles cover the fan: Phi is linear in r there
    phi = jnp.where((r_edges >= NF_R_MIN)[..., None, None], phi, gg.nf_phi0 * (r_edges / NF_R_MIN)[..., None, None])
    return jnp.moveaxis(phi[:, 1:] - phi[:, :-1], (0, 1), (2, 3))


def _distributed(ctx, gg, el, frus, names):
    """Volume backscatter and multiple scattering along each ray: density per metre of outbound range,
    ``1/r`` (asinh over each node, exact), per return elevation, until the ray's far edge. With
    :data:`NEAR_FIELD_APERTURE` the near field is the aperture's (:func:`_near_field`)."""
    p, geom, nodes = ctx.params, ctx.geom, ctx.nodes
    S, Z, A = geom.ray_length.shape
    J = el.c.shape[0]
    s_j = (1.0 / el.c_out + 1.0 / el.c) / nodes.c1  # (J,) seconds per metre of outbound range
    tau = nodes.t - p.emission_time_s  # (K,)
    r = tau[None, :] / s_j[:, None]  # (J, K)
    dr = nodes.h / s_j[:, None]
    r0 = NEAR_FIELD_PER_THICKNESS * gg.thickness_m
    fall = (jnp.arcsinh((r + 0.5 * dr) / r0) - jnp.arcsinh((r - 0.5 * dr) / r0))  # integral of 1/sqrt(r^2+r0^2)
    rp = jnp.maximum(r, 0.0)
    mu_t = p.mu_s_per_m + p.mu_a_per_m
    terms = []  # (weight, density (J, K)) per term
    if "volume" in names:
        att = jnp.exp(-mu_t * rp * (1.0 / el.c_out + 1.0 / el.c)[:, None])
        terms.append((1.0, p.volume_backscatter_fraction / (2.0 * math.pi) * p.mu_s_per_m * att * el.dmu[:, None]))
    if "multiple_scattering" in names:
        build = -jnp.expm1(-2.0 * p.mu_s_per_m * rp)
        att = jnp.exp(-p.mu_a_per_m * rp * (1.0 / el.c_out + 1.0 / el.c)[:, None])
        if MS_DERIVED and gg.ms_c2d is not None:
            # the coupling per zone: the zone's in-plane view of the fan times the slab's arccos(1 / n1)
            coupling = ((p.multiple_scattering / MS_REFERENCE) * jnp.arccos(1.0 / p.n1) * gg.ms_c2d)[:, :, None]
        else:
            coupling = p.multiple_scattering
        terms.append((coupling, 1.0 / (4.0 * math.pi) * p.mu_s_per_m * build * att * el.dmu[:, None]))
    # coverage: each ray's weight (its angle and the aperture's projection) until its far edge (a ray that leaves
    # the guide at once, from a sensor at a corner, carries none)
    wray = jnp.where(geom.ray_length > 0, gg.cos_sensor * gg.dphi[None, :, None] / (gg.fov * gg.thickness_m), 0.0)
    end_t = p.emission_time_s + geom.ray_length[:, :, None, :] * s_j[None, None, :, None]  # (S, Z, J, A)
    wrep = jnp.broadcast_to(wray[:, :, None, :], end_t.shape)
    ended = _weighted_step(end_t.reshape(S, Z * J, A), wrep.reshape(S, Z * J, A), nodes).reshape(S, Z, J, -1)
    if NEAR_FIELD_APERTURE and gg.nf_tab is not None:
        # every ray's light in every zone over each node (the aperture's near field, from the emission on: the
        # node that straddles it takes the ranges after it); the rays that have ended are taken off with the far
        # field's 1/r (a ray ends at a wall, far from the sensor)
        edges = jnp.maximum(jnp.concatenate([r - 0.5 * dr, r[:, -1:] + 0.5 * dr], axis=-1), 0.0)  # (J, K + 1)
        near = _near_field(gg, edges)  # (S, Z, J, K)
        geo = jnp.maximum(near - ended * fall, 0.0)
    else:
        start = jnp.reshape(p.emission_time_s, (1, 1, 1))
        emitted = _weighted_step(start, jnp.ones((1, 1, 1), nodes.t.dtype), nodes)[0, 0]  # (K,)
        total = jnp.sum(wray, axis=-1)[:, :, None, None]
        geo = jnp.maximum(emitted * total - ended, 0.0) * fall  # (S, Z, J, K)
    if frus is not None:
        # beyond a skin contact, the zone loses what its rays lose out and back (the far edge's
        # factors, averaged over the zone's rays, per return elevation), from its distance on
        P_out, P_ret, along = frus
        loss = 1.0 - jnp.mean((1.0 - P_out)[..., None] * (1.0 - P_ret), axis=2)  # (S, Z, N, J)
        dist = ctx.contacts.distance  # (S, N)
        step = jax.nn.sigmoid((rp[None, :, :, None] - dist[:, None, None, :]) / p.touch_radius_m)  # (S, J, K, N)
        geo = geo * jnp.prod(1.0 - jnp.moveaxis(loss, 2, 3)[:, :, :, None, :] * step[:, None], axis=-1)
    elif ctx.contacts is not None and ctx.shadowing:
        from .components import shadow

        rr = jnp.broadcast_to(rp.reshape(-1), (S, Z, rp.size))
        geo = geo * shadow(rr, ctx.contacts, p).reshape(S, Z, J, -1)
    mass = sum(w * jnp.einsum("szjk,jk->szk", geo, dens) for w, dens in terms)
    return p.gain[:, None, None] * smooth_like_deposit(mass)


def guided_node_masses(ctx, gg: GuidedGeometry, components, separate: bool) -> dict:
    """The guided optics' counts at the time nodes, before the pulse (the hook of ForwardModel)."""
    p = ctx.params
    el = _elevations(gg, p.n1)
    skin_contacts = gg.skin is not None and ctx.contacts is not None
    frus = _frustration(ctx, gg, el) if skin_contacts else None
    # shadowing switched off: contacts only add light
    frus_shadow = frus if ctx.shadowing else None
    out = {}
    dist = [n for n in components if n in ("interface", "volume", "multiple_scattering")]
    if "interface" in dist:
        # roughness backscatter: no guided model of it; the default optics' term
        from . import components as C

        cov = _default_coverage(ctx)
        out["interface"] = C.smooth_like_deposit(cov * C.interface(ctx))
    g_dist = [n for n in dist if n != "interface"]
    if g_dist:
        eld = _elevations(gg, p.n1, distributed=True)
        # the contacts' losses at the distributed terms' own return elevations (lost per elevation)
        frus_d = None if frus_shadow is None else _frustration(ctx, gg, eld)
        if separate:
            for n in g_dist:
                out[n] = _distributed(ctx, gg, eld, frus_d, (n,))
        else:
            out["distributed_guided"] = _distributed(ctx, gg, eld, frus_d, tuple(g_dist))
    for name in components:
        if name == "end":
            if ctx.contacts is not None and not ctx.shadowing:
                out[name] = _edge(ctx._replace(contacts=None), gg, el, None)
            else:
                out[name] = _edge(ctx, gg, el, frus_shadow)
        elif name == "touch" and p.n_touches:
            if skin_contacts:
                out[name] = _touch(ctx, gg, el) + (_touch_diffuse(ctx, gg, el) if SECOND_ORDER else 0.0)
            else:
                out[name] = _touch_free(ctx, gg, el)
        elif name == "crosstalk":
            from .components import crosstalk

            out[name] = crosstalk(ctx)
    return out


def _default_coverage(ctx):
    from . import components as C

    p, nodes = ctx.params, ctx.nodes
    emitted = C.step_on(jnp.reshape(p.emission_time_s, (1, 1, 1)), nodes)
    ended = C.step_on(ctx.end_times, nodes)
    return p.gain[:, None, None] * jnp.clip(emitted - ended, 0.0, 1.0)

