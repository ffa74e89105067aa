"""The lenslet-statistics fit: the exact forward model fitted to per-lenslet moments.

``method="lenslet"`` (docs/distance.md, "The lenslet fit"). The per-pixel fit
(:func:`lfcam.measure.pointfit.fit_point_image`) compares a rendered patch with the data
pixel by pixel; this fit compresses both sides the same way first. For every lenslet whose
micro-image touches the region's box it keeps four linear moments of the pixels the lenslet
map (:class:`lfcam.measure.LensletMap`) gives that lenslet:

    m0 = Σ v,   m1 = Σ v·dx,   m2 = Σ v·dy,   m3 = Σ v·(dx² + dy²)

(dx, dy: pixel centre minus micro-image centre, in pitches). The moments are linear in the
image, so the unknown intensity scale is still solved in closed form, and they are computed
from the *same pixels* on both sides: the model traces rays exactly through the thick lens,
crosses the lenslet whose cell it hits, lands at ``C + f_x·slope``, is binned to the pixel
that contains it (the sensor integrates: the half-pixel centroid shifts of 2–4 px spots behind
focus are modelled, not assumed away), looked up in the same lenslet map and dropped where the
data has no pixel (sensor edge, seams, outside the box). No threshold is involved.

Each ray stands for a patch of the pupil: near a lenslet-cell border (MLA) and near a pixel
border (sensor) it is shared across the border by a box of the local ray spacing, so that the
moments are continuous in the source position (hard binning is the limit of a vanishing box).

Cost: a model evaluation is one trace of 1 k–20 k rays (Vogel-spiral pupil sample:
quasi-random, no grid aliasing against the pixels) and four ``bincount`` — 0.5–3 ms. Fit
(:func:`fit_lenslet_point`): a batched distance scan of a smooth summary (slope-field gain,
footprint centroid and size), Broyden matching of that summary from the best starts,
Levenberg–Marquardt on the moments with a coarse model, Gauss–Newton steps with the fine model,
and a polish with ``POLISH_RAYS`` only where the fine fit has not settled (:func:`_settled`).
Lines (:func:`fit_lenslet_line`): equally bright points along a segment (at most
``LINE_SPACING_PITCH`` apart on the MLA, 12–48), 5 parameters, started from the point fit and
from a distance scan. Point or line is decided from the two misfits (:func:`measure_lenslet`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from functools import partial
from typing import NamedTuple

import cv2
import numpy as np

from lfcam.camera import CameraProfile
from lfcam.measure import solve as least_squares
from lfcam.measure.base import (
    LINE_SIGMA_FLOOR_REL,
    Measurement,
    line_measurement,
    point_measurement,
)
from lfcam.measure.cache import ObjectCache
from lfcam.measure.geometry import Geometry
from lfcam.measure.noise import NoiseModel, capture_noise, clipped_mean, moment_noise_sums
from lfcam.measure.pointfit import LocalLattice, chief_ray_gains, chief_ray_offset
from lfcam.measure.regions import Region
from lfcam.measure.sampling import pixel_boxes, ray_share, segment_points, vogel_disc
from lfcam.measure.solve import (
    fd_jacobian,
    gauss_newton_fixed,
    gram,
    jt,
    levenberg_marquardt,
    linear_step,
    log_distance_sigma,
    sq,
)
from lfcam.measure.verify import line_beats, line_trigger, poor_fit_limit
from lfcam.optics.trace import trace_sources_fast
from lfcam.robust import NORMAL_MAD_SCALE
from lfcam.status import RegionStatus

RAYS_PER_LENSLET = 160  # pupil samples per lit lenslet (clipped to MIN_RAYS … MAX_RAYS)
MIN_RAYS = 12000
MAX_RAYS = 20000
COARSE_RAYS = 3000  # rays per evaluation while the basin is found
SCAN_RAYS = 1000  # rays per evaluation of the distance scan
COARSE_PER_LENSLET = 25  # ... at least this many per lit lenslet
SCAN_DISTANCES = 28  # geometric distance scan, 1.1 f … 30 m
SCAN_KEEP = 2  # starts matched on the summary ...
START_HOPELESS = 0.9  # ... but a later start whose scan-model misfit² is over this is not,
START_GOOD = 0.01  # ... once an earlier start's coarse misfit² is under this: over 276
#                    regions (seed, point grid, 12-source scenes) 39 such starts were skipped,
#                    none a winner (docs/distance.md, "Starts that miss the data")
COARSE_ITERATIONS = 6
COARSE_CELLS_FTOL = 0.02  # ... on the cells it ends on an iteration that lowers its misfit² by
#                           less than this share: a line's blur fitted as a point creeps down
#                           through all of them, by a median 0.3 % an iteration after the first
#                           (at most 5.5 %; hexagonal grid lines at 0.19-0.95 against noise
#                           misfits of 0.001-0.13), which only the line fit changes
#                           (docs/distance.md, "The point's coarse stage on a line's blur
#                           (stop 50)")
COARSE_STEPS = np.array([0.01, 3e-4, 3e-4])  # log distance, x/L, y/L: difference steps, at most
LATERAL_STEP_BLUR = 0.005  # a point's lateral difference step moves its blur on the MLA by at
#                            most this × the blur's diameter (point_steps)
COARSE_RECENTRE_MIN_LIT = 150  # on a blur lighting this many lenslets or more, the coarse
#                                stage's end on the rays is moved sideways by one centroid step
#                                (_recentre_coarse), kept where it lowers the coarse misfit: its
#                                difference steps can leave a large blur 0.2 pitch aside, where
#                                the misfit is 8 × its minimum's (the Illum-size scene's
#                                1 533-lenslet point: only the polish left 0.23, 1.21 M rays;
#                                with the step 0.61 M). On smaller blurs it moved 69 of 360
#                                12-source answers with no gain: docs/distance.md, "A large
#                                blur's coarse end moved onto its light (stop 74)")
COARSE_RECENTRE_MIN_PITCH = 0.05  # ... where the light centroids lie this many pitches apart
#                                   on the MLA or more (a step shorter is not evaluated)
SUMMARY_ITERATIONS = 4
SUMMARY_SCAN_FIRST = True  # a start on the cells is matched on the scan's rays first (4× cheaper
#                           an evaluation than the coarse cells), and on the cells, from there
#                           with that match's Jacobian, only where the summary was matched:
SUMMARY_MATCHED = 0.05  # ... its normalised misfit under this: a point's blur (0.004-0.065 on the
#                         focus grid's points), not a line's, which a point's summary cannot
#                         match (0.04-0.27 on the grid's lines, most over 0.06; either side of
#                         it costs only time: docs/distance.md, "The summary matched on the
#                         scan's rays (stop 57)")
SUMMARY_SAME_LOG = 0.01  # a start whose scan match lands within this (log distance) and
#                         SUMMARY_SAME_ANGLE (x/L, y/L) of an earlier start's is that start's
#                         basin: it is not matched on the cells again (docs/distance.md, "One
#                         cells match a basin (stop 58)")
SUMMARY_SAME_ANGLE = 1e-3
SUMMARY_RECENTRE_ABOVE = 1.0  # a match that leaves the summary's normalised misfit over this
#                               (no step of it lowered that: a start near focus, where the
#                               slope gain's difference step crosses it) is followed by lateral
#                               steps alone, the model's light centroid onto the data's
#                               (focus grid: points ≤ 0.065; 91 point fits of the 231 lines
#                               1.0-35, 2 of them moved, every line's answer the same; a
#                               caustic-cut point of the Illum-size scene 3.19, its start
#                               aside and its fit lost: docs/distance.md, "A start moved onto
#                               the light (stop 60)")
SUMMARY_RECENTRE_STEPS = 2  # ... at most this many (the least misfit of them is kept ...
SUMMARY_RECENTRE_GAIN = 0.5  # ... where its misfit² is under this × the start's: a line's
#                              blur, which no point's summary matches (380 mm lines: 2.0), is
#                              left where it was (misfit 0.667 → 0.665 there; the caustic-cut
#                              point: 0.82 → 0.17)
SUMMARY_LARGE_RAYS = COARSE_RAYS  # a ray-sampled blur lighting LINE_BIN_MIN_LIT lenslets or
#                                   more matches its summary on this many rays, not on the
#                                   coarse model's (docs/distance.md, "A large line's coarse
#                                   stage on super-cells (stop 76)"); 0: the coarse model's
FINE_ITERATIONS = 4
FINE_MIN_TRIAL_LOG = 1e-4  # ... and no step (nor halving of a failed one) under this log
#                            distance is tried (a third of SIGMA_FLOOR_REL): the fine model's
#                            ray noise decides those (system 2's 1 200-1 450-lenslet blurs at
#                            300 mm halved failed steps to 0.6-0.7e-4, twice a fit); the 108
#                            points' rays traced -7.8 % (docs/distance.md, "Steps under the σ
#                            floor (stop 50)")
FINE_LM_ITERATIONS = 6  # Levenberg–Marquardt iterations of the polish (its own Jacobian), at
#                         most: a sharp minimum ends in 1-3 (POLISH_SETTLE_LOG); along a flat
#                         valley 3 stopped mid-way (a 12-source scene's 3500 mm blur: +2.9 or
#                         +20 % by the path, its minimum at +4.4 %, σ 3.7 %)
LINE_SETTLE_LOG = 2e-5  # the line's fine fit ends on a step under this in log distance
LINE_FINE_LM_ITERATIONS = 3  # ... and of the line (2: lines grid 0.134 → 0.156 % mean, 8 ms saved)
LINE_FINE_TRIAL_LATERAL = 0.5  # the ray-sampled line's fine LM tries no step under
#                                 LINE_REFIT_MIN_TRIAL_LOG in log distance and this share of
#                                 a difference step in each lateral angle: it ends there
#                                 (0: no such rule)
LINE_FINE_FAIL_STOP_LOG = 1.5e-3  # ... and ends at a trial that fails to lower its misfit while
#                                   moving the log distance by under this (LINE_SETTLED_LOG's
#                                   size: the fine sample's own noise) and the source sideways
#                                   by under LINE_FINE_TRIAL_LATERAL of a step: on scene (b)'s
#                                   ten lines its first trials of 4e-4-1.5e-3 failed (misfit
#                                   +0.3-4.9 %) and their 2-3 damped repeats too, or lowered it
#                                   by 0.1 % (docs/distance.md, "A line's fine fit ends at its
#                                   first short failed trial (stop 79)")
LINE_REFIT_EARLY = True  # on the rays the settled test is read before the fine fit's last
#                          iteration, and a line it refits goes to the refit from there
#                          (docs/distance.md, "The settled test before the fine fit's last
#                          iteration (stop 58)")
POLISH_RAYS = 80000  # rays of the polishing model
POLISH_SETTLE_LOG = 2e-5  # the polish ends when its next undamped step moves the log distance
#                           by less than this (0.002 %; docs/distance.md, "A polish that
#                           stops when its step is nothing")
POLISH_MIN_TRIAL_LOG = FINE_MIN_TRIAL_LOG  # ... and tries no step under this that
#                              would lower its misfit² by less than SETTLED_GAIN (a settled
#                              test's step), where it is for the settled test: near a gate every
#                              step that lowers the misfit counts (scene (b): one of its sources
#                              poor-fit otherwise; docs/distance.md, "The polish's steps under
#                              the σ floor (stop 51)")
POLISH_NOISE_SHARE = 0.1  # the polish runs on as few rays as keep the model's own ray noise
#                            at this share of the region's noise misfit (at least the fine
#                            model's, at most POLISH_RAYS: _polish_rays): photon-limited points
#                            whose valley the polish walks (20 noise draws of the 12-source
#                            captures, 1 440 fits: mean 26.6 -> 22.7 ms, over 50 ms 55 -> 22,
#                            mean z² × 1.008 [0.974, 1.044]; bright points unchanged;
#                            docs/distance.md, "The polish's rays where photons dominate (stop
#                            62)")
POLISH_FIRST_OR_STOP = True  # a polish the settled test asked for ends where it began when its
#                              first step (the fine model's Jacobian's, on the polishing model's
#                              residual) does not lower the misfit: on the 108 grid points 8 of
#                              77 polishes, whose damped trials and difference Jacobian then
#                              moved the answer by at most 0.03 % in ~6 evaluations of 80 000
#                              rays (docs/distance.md, "A polish whose first step fails (stop
#                              57)")
POLISH_CONFIRM_NOISE = 1.5  # a polish that its secant (Broyden) Jacobian calls settled while
#                             its misfit is over this × the region's noise misfit goes on with
#                             the fine model's Jacobian by differences (0: never): the secant's
#                             distance column can be stale. Scene (b)'s 906.7 mm point stopped
#                             +0.26 % off at σ 0.037 % (misfit 0.120 against 0.027 at the
#                             truth) and tried a line for 142 ms. (The noise misfit is an
#                             upper bound: at 1 × it four more of scene (b)'s points went on,
#                             15-26 ms each, to move within a third of their σ; docs/
#                             distance.md, "A polish that a stale secant stopped (stop 67)")
POLISH_CONFIRM_BELOW = 1e-3  # ... where its σ (log distance) is under this: a dim point's
#                              polish confirmed moves within its σ and its pixel polish's start
POLISH_NEAR_GATE_FINE_JAC = True  # a polish near a gate starts from the fine model's Jacobian
POLISH_BY_TOLERANCE = True  # with a tolerance, a point is polished only where the fine fit's
#                             answer does not meet it (point_fit_stages' ``accept``; the 108
#                             points at 1 %: 26.6 -> 23.0 ms a region, docs/distance.md, "A
#                             polish only where the tolerance needs it (stop 51)")
SETTLED_LOG = 5e-4  # the fine fit has settled: two pupil phases agree on the distance to
# within this (log distance, 0.05 %, ~ the polish's own sampling noise) and a further step would
# move it by less than half of it
SETTLED_GAIN = 0.05  # ... and lower the misfit² by less than this share, on a minimum whose
SETTLED_SIGMA = 1e-3  # statistical σ (log distance) is under this: a shallower one is polished
SETTLED_TURNED_LINEAR = True  # the turned sample's landing read from the two samples' linear
#                                steps from the fine fit's start with its Jacobian (the shift
#                                between their minima, as a line's settled test reads it), not
#                                from its own evaluated Gauss–Newton steps: on scene (b)'s 55
#                                points that reach it the same verdicts, the shift equal to the
#                                landing's to 5e-16 (median; 1.9e-4 at most), one evaluation
#                                fewer (docs/distance.md, "A point's settled test from the
#                                linear steps (stop 79)")
POLISH_NEAR_GATE = 1.0  # settled point fits are polished all the same when their misfit is
# over this share of the line trigger or the poor-fit limit (the gates that read it; the
# two-source try's, lfcam.distance, lies over the trigger on a capture with noise): the
# polish, which only lowers it, may take it under; under both the verdicts are the same
# polished or not (0.7 until stop 73: docs/distance.md, "A polish only where a gate could
# change (stop 73)")
LINE_JACOBIAN_ENDS = True  # on the cells a line's Jacobian along it from its two end points
#                           (line_model; docs/distance.md, "A line's Jacobian along it from
#                           its ends (stop 56)")
LINE_TURNS = True  # each point of a line model turns its pupil sample (LensletModel.turns)
LINE_POINTS = 12  # points of the line model, at least (and the count the ray budgets are for)
LINE_POINTS_MAX = 48  # ... at most
LINE_SPACING_PITCH = 0.5  # their spacing on the MLA, at most (lenslet pitches)
LINE_SCAN_POINTS = 12  # points of the distance scan's line model, at most (and of its turned
#                        starts), each with the coarse stage's rays a point: the scan only picks
#                        the start nodes, 23 % apart (24 until stop 47: of 231 grid lines 17
#                        moved, by 0.001-0.04 % on system 2 and 0.08-0.11 % (⅓σ) on two of
#                        system 1's; −3 to −10 % CPU a region; docs/distance.md, "Fewer points
#                        in the distance scan (stop 47)")
LINE_SCAN_POINTS_SMALL = 6  # ... and on a blur lighting fewer than LINE_SCAN_SMALL_LIT lenslets
LINE_SCAN_SMALL_LIT = 100  # (the line tries of point blurs: ~4 ms less each, the same answers;
#                            on large blurs 6 points' fewer rays misled the scan: docs/distance.md,
#                            "A smaller scan for small blurs (stop 48)")
LINE_COARSE_POINTS = 24  # points of the coarse stage's line model, at most
LINE_START_ANGLES = 6  # a line's start: its axis turned in steps of 180° / this ...
LINE_START_EXTRA_PITCH = 2.0  # ... each at its measured length and this many pitches longer,
LINE_TURNED_STARTS = 2  # ... the best this many of them by the scan model (1: a line 2 pitches
#                          long at 2900 mm stayed a spot, 1.39 % off)
LINE_TURN_BELOW = 0.05  # ... when the footprint's elongation (λ₁ − λ₂)/(λ₁ + λ₂) is under this
LINE_STRETCHED = 0.1  # a point footprint elongated more (off axis): the line's starts turn
LINE_STRETCH_MIN_LIT = 40  # ... on blurs of this many lit lenslets or more
LINE_STRETCH_AXIS_DEG = 20.0  # ... whose footprint's axis is within this of the stretch's
LINE_SCAN_RECENTRE = 1  # where the frame's edge cuts a region, the line's scan segments are
#                          moved this many times so that the scan model's light centroid on the
#                          region's lenslets is the data's (the visible part's centroid lies off
#                          the source's chief ray: scene (b)'s 1 131 mm line, scanned 16 % long
#                          and poor-fit on 10 of 11 draws; docs/distance.md, "A line the frame's
#                          edge cuts (stop 69)")
LINE_RACE_ITERATIONS = 2  # several starts race this many coarse iterations; the leader goes on
LINE_WARM_ITERATIONS = 0  # a line refitted from an earlier answer: coarse iterations, at most
#                           (0: its coarse Jacobian alone, then the fine stage; 6, as a lone
#                           start: a line touching a point, its regions 141-227 ms against
#                           98-213, the answers within 0.03 % of these: docs/distance.md, "A
#                           refit from the first answer (stop 72)")
LINE_CELLS_RACE_ITERATIONS = 1  # ... on the cells, where the coarse stage's own Gauss–Newton
#                                 steps go on from the leader (168 grid lines: the same answers
#                                 but one, 3-10 ms less a line; docs/distance.md, "Cells
#                                 integrated whole (stop 43)")
LINE_RACE_HOPELESS = 100.0  # the starts race from the best placed; one whose misfit² where
#                             it starts is over this × the best race's end is not raced (a
#                             380 mm line in front of a 1 m focus: 3 of its 4 starts, 0.16-0.21
#                             against 0.0007; 0.22 -> 0.18 s, the same answer) ...
LINE_RACE_START_RATIO = 5.0  # ... nor one whose misfit² where it starts is over this × the
#                              best start's: over the 64 ray-sampled races of the 231 grid
#                              lines with two starts or more, the winner started within 2.9 ×
#                              the best start's misfit², and 35 turned axes (system 1's lines
#                              far off axis behind focus, system 2's at 720 mm) 10-100 × it
#                              (docs/distance.md, "Starts that cannot win the race (stop
#                              50)"); 10 until stop 61, when the scan's start on the crowded
#                              scene's large lines in front of focus, 5.5-7.3 × and ~20 ms a
#                              heat, the independent renderer's 1500 mm lines, 7.9-8.2 ×, and
#                              15 heats of the grid's lines, 5-10 ×, never won either
#                              (docs/distance.md, "A tighter race (stop 61)")
LINE_RACE_GIVE_UP = 15.0  # ... and a heat whose misfit² after an iteration is over this ×
#                           the best earlier heat's end runs no more (ray-sampled races of the
#                           231 grid lines: winners at most 9.1 ×; docs/distance.md, "Heats
#                           that cannot win (stop 51)")
LINE_MIN_SHARE = 0.5  # more points share the 12 points' rays, down to this share a point
LINE_MIN_RAYS = 64  # rays a point, at least
LINE_COARSE_SHARE = 12  # the line's distance scan traces COARSE_RAYS / this per point
LINE_COARSE_PER_LENSLET = 3  # rays a point of the line, per lit lenslet: coarse model ...
LINE_COARSE_MAX_RAYS = 4500  # ... at most
LINE_FINE_RAYS = POLISH_RAYS // (2 * LINE_POINTS)  # ... and fine model, the 12 points' rays a
#                   point on every blur (half the point polish's rays; every point's pupil sample
#                   turned, LINE_TURNS: with one shared sample lines far behind focus and off
#                   axis stalled 1-2 % off on the ripple of the model's own ray sample;
#                   docs/distance.md, "Lines off axis" and "A line's points, each with its own
#                   turn of the pupil sample"). Until stop 54 it grew with the blur (15 rays a
#                   lit lenslet, up to 18 000, and its Gauss–Newton steps on 5 a lit lenslet):
#                   at stop 51 the floor put scene (b)'s large line blurs 0.1-0.25 % long; with
#                   the code of stop 54 they stay within 0.104 % (σ 0.10 %), with one sharing
#                   box or two (docs/distance.md, "The line's fine sample at its floor (stop
#                   54)")
LINE_SETTLED_LOG = 1.5e-3  # a line's fit has settled when a Gauss–Newton step through a
#                             turned pupil sample moves its log distance by less than this
#                             (√2 × the line σ floor: the two samples' shifts add); else ...
LINE_REFINE = 4.0  # ... it is refitted with this × the fine model's rays a point (8× until
#                      stop 53: with the shares of RAY_SHARE_RICHARDSON 4× left the refit
#                      lines' noise-free answers as close (docs/distance.md, "Ray shares
#                      without the box's variance (stop 53)") ...
LINE_REFINE_MAX_RAYS = 40000  # ... at most this many (docs/distance.md, "A line's settled test",
#                               "A line's points, each with its own turn of the pupil sample")
LINE_REFIT_ENDS = True  # ... and takes its Jacobian along the line from the line's two end
#                          points (line_model's ``traced_ends``: two traces of the line and two
#                          points, not three traces; system 1's 24 far lines −5 % CPU, mean |error|
#                          0.187 % either way: docs/distance.md, "The refit's Jacobian from the
#                          line's ends (stop 78)")
LINE_BIN = 2  # a ray-sampled line blur lighting LINE_BIN_MIN_LIT lenslets or more: its coarse
#                stage (race and leader) fits the moments summed over super-cells of this ×
#                this lattice cells (:class:`CellBins`) on LINE_BIN_RAYS × fewer rays, and the
#                fine stage's Gauss–Newton steps (the coarse Jacobian's) read them too; the
#                fine stage's Levenberg–Marquardt, the settled test and the refit read every
#                lenslet (docs/distance.md, "A large line's coarse stage on super-cells (stop
#                76)"); 1: no super-cells
LINE_BIN_MIN_LIT = 200
LINE_BIN_RAYS = 4.0
LINE_FINE_BY_TOLERANCE = True  # with a tolerance, a line on super-cells ends after its fine
#                                Gauss–Newton steps where the caller accepts its answer there
#                                (scene (b)'s 10 lines at 1 %: 12.4 -> 10.1 M rays; docs/
#                                distance.md, "A line on super-cells that ends where the
#                                tolerance accepts it (stop 77)") ...
LINE_EXIT_STEP_LOG = 0.01  # ... where its linear step to the two samples' mean minimum moves
#                            the log distance by no more than this (scene (b): ≤ 0.0012; a
#                            longer step is the linear model's to judge no more)
LINE_CELLS_MIN_LIT = 100  # a line blur lighting this many lenslets or more is modelled with
#                           samples fixed on the lenslet cells (LensletModel(cells=n)):
LINE_CELLS_PROBE_LOG = (-0.12, 0.0, 0.22)  # ... where they apply at these log distances from
#                                            each start's (3 points of the line at each; −0.22
#                                            kept system 2's 1500 mm lines off: 0.42-0.46 s,
#                                            0.13-0.16 s on the cells)
LINE_AT_COARSE = True  # on the cells a line is tried at the point fit's coarse stage already
#                       where its floor is over the trigger (measure_lenslet)
POINT_CELLS = True  # a point blur lighting LINE_CELLS_MIN_LIT lenslets or more is fitted on the
#                    cells too where they apply at LINE_CELLS_PROBE_LOG about its best start
#                    (each start matched on them where they apply about it): its first look
#                    on the coarse, fine and settled models' n as the line's; its answer then
#                    from the rays, started there (docs/distance.md, "Large point blurs on
#                    the cells (stop 44)")
LINE_CELLS_COARSE = 2  # ... n of the coarse stage's model,
LINE_CELLS_FINE = 4  # ... of the fine model,
LINE_CELLS_FINE_WHOLE = 3  # ... of the fine model where the cells lit whole are integrated
#                            whole (CELLS_WHOLE, rectangular lattice): the settled test's
#                            answers within 0.008 % of n = 4's (8 noise-free lines: mean
#                            |error| 0.013 % against 0.014 %), 14 ms less a line
#                            (docs/distance.md, "Cells integrated whole (stop 43)")
LINE_CELLS_SETTLE = 6  # ... of the settled test's model (the answer steps to its minimum),
LINE_CELLS_COARSE_STEP_LOG = 1e-3  # ... the coarse Gauss–Newton steps end on a step under this
#                                   (log distance; the n = 2 model's own bias is 0.4-0.7 %)
LINE_CELLS_JACOBIANS = 3  # ... and take their Jacobian at most this many times (again after
#                           LINE_CELLS_GN_STEPS steps whose next is still over that)
LINE_CELLS_GN_STEPS = 3
LINE_CELLS_FINE_STEP_LOG = 3e-4  # ... the fine model's end on a step under this (the settled
#                                  test's step takes the rest: docs/distance.md, "Fewer
#                                  evaluations on the cells (stop 39)")
LINE_CELLS_REFIT = 8  # ... and of the refit (docs/distance.md, "Samples fixed on the lenslet
#                        cells")
LINE_REFIT_STEPS = 3  # ... by the refit model's Jacobian, taken once, and at most this many
#                       Gauss–Newton steps with it (2 Levenberg–Marquardt iterations, a fresh
#                       Jacobian at each, until stop 40: 25-30 % of the line's CPU more, the
#                       answers within 0.12 %: docs/distance.md, "Cheaper stages (stop 40)")
LINE_REFIT_STEP_LOG = 1e-4  # ... ending on a step under this (log distance; on the rays the
#                             larger LINE_REFIT_MIN_TRIAL_LOG below rules)
LINE_REFIT_MIN_TRIAL_LOG = LINE_SIGMA_FLOOR_REL / 3  # ... and trying no step (nor halving of a
#                       failed one) under this: on system 1's lines far off axis behind focus
#                       the refit's steps after its first were 1-5e-4, at misfit changes of
#                       0.01-0.4 % either way (its model's ray noise), 12 ms an evaluation
#                       (docs/distance.md, "The refit's steps under the line σ floor (stop 51)")
LINE_REFIT_TRUSTED = True  # ... whose first step, taken by that Jacobian where it moves the log
#                             distance by under LINE_REFIT_TRUST_LOG, is not evaluated: the
#                             answer's residual is the linear model's (r + J·dq, the step dq).
#                             Of 17 refits (system 1's 24 far lines, scene (b)'s ten) every
#                             first step lowered the misfit at its first try and every second
#                             one was under LINE_REFIT_MIN_TRIAL_LOG (not tried); the linear
#                             model's misfit was within 1.1 % of the evaluated one, its σ within
#                             3.6 %
#                             (docs/distance.md, "The refit's step by its own Jacobian, not
#                             evaluated (stop 79)")
LINE_REFIT_TRUST_LOG = 0.01  # (those first steps: 0.03-0.69 % in distance)
LINE_RAYS_FINE_GN = False  # a ray-sampled line's fine stage (not on super-cells) takes no
#                            Gauss–Newton steps on the coarse Jacobian before its
#                            Levenberg–Marquardt: on system 1's 24 far lines those four steps
#                            (0.08-4.5 % in all) fell short of where the fine model's own
#                            Jacobian then went (up to 9.8 % on, in 16 of them): the same
#                            accuracy, 8 % less CPU (docs/distance.md, "A ray-sampled line's
#                            fine stage without the coarse Jacobian's steps (stop 80)")
LINE_FINE_ENDS = True  # a ray-sampled line's fine Jacobian (not on super-cells) takes its
#                        columns along the line from the line's two end points, as the refit's
#                        (LINE_REFIT_ENDS): 5.8 % fewer rays on system 1's 24 far lines, 0.95-0.97
#                        × their CPU, the same accuracy (on super-cells it moved scene (b)'s
#                        lines: docs/distance.md, "Two more line paths tried (stop 79, not
#                        kept)", "The fine Jacobian from the line's ends off super-cells (stop 80)")
LINE_CELLS_TRUSTED = True  # the cells' fine Gauss–Newton step (the fine model's own Jacobian)
#                             is not evaluated either where under LINE_REFIT_TRUST_LOG: the
#                             line regions' seven cells lines each took one step and no second
#                             (docs/distance.md, "The refit's step by its own Jacobian, not
#                             evaluated (stop 79)")
LINE_CELLS_POINTS_SHARE = 0.5  # on the cells, the coarse and fine models' line has this share
#                                of the points (LINE_POINTS at least): the settled test's
#                                model keeps them all, and the answer goes to its minimum (the
#                                fine model's minimum moves by 0.05-0.08 % with half of them)
LINE_CELLS_COARSE_POINTS = 8  # ... and the coarse stage's (and its race's) a third of them, at
LINE_CELLS_COARSE_SHARE = 1 / 3  # least this many: it only finds the basin, which the fine
#                                  stage leaves (the 4 noise-free hexagonal lines 108 → 94 ms,
#                                  the 8 rectangular 75 → 71 ms, the same answers within 0.005 %;
#                                  docs/distance.md, "Fewer points in the coarse stage (stop 46)")
LINE_CELLS_COARSE_GAIN = 0.05  # ... the coarse stage takes no further Jacobian after a round
#                                 of steps that lowered the misfit² by under this share, or
#                                 where the next step would, by its Jacobian's prediction
LINE_CELLS_SETTLED_LOG = 5e-3  # ... the settled test's step is taken as it is up to this; a
#                                 longer one by Gauss–Newton steps on the settled test's model
LINE_CELLS_SETTLE_STEPS = 3  # ... at most this many (the refit of the rays is for their
#                              sample's noise, which the cells do not have)
# Point or line, decided from the data (docs/distance.md, "The misses fixed").
# Measured relative misfits of the moments: a point source fitted as a point 0.0006-0.011
# (photon noise of the data: 0.002-0.005 measured from two renders of the same scene; up to
# 0.08 for a far source that gets 2-4 % of the light of the scene's brightest), a line
# fitted as a point 0.15-0.69, a line fitted as a line 0.001-0.04.
LINE_TRIGGER = 0.0015  # a point misfit over this and over its noise and model triggers
#                        (below): also fit a line (lfcam.measure.verify.line_trigger;
#                        noise-free seed captures: points leave 0.0001-0.0039, 10 mm lines as
#                        points 0.0018-0.29)
LINE_MODEL_FACTOR = 2.0  # ... and over this × the point models' own disagreement at the fit
#                          (LensletFit.model_misfit: the fine and polishing models' ray samples;
#                          points leave at most 1.07 × it on the seed, lines as points 2.9 × and
#                          more; noise-free points over the floor tried lines that could not win)
LINE_NOISE_FACTOR = 1.3  # ... and over this × its noise misfit (verify.line_trigger; 2.0 left
#                          lines 2 pitches long 2200-2900 mm behind a 1 m focus as points at
#                          1.6-1.7 ×, 0.4-1.4 % off; real points leave 0.3-1.5 ×)
LINE_WITHIN_NOISE = 1.0  # ... but not for a point whose misfit is within this × its noise misfit
#                          (over the trigger only where that is capped: dim blurs; no line
#                          can win against noise, and the 168 grid lines leave ≥ 1.57 × as
#                          points; docs/distance.md, "No line try inside the noise (stop 65)")
LINE_GAIN = 0.5  # ... a line only when it cuts the point's misfit below this × (two more
#                  parameters cannot halve a misfit that is noise; a coma-stretched point's
#                  line fit does not lower it at all)
LINE_STOP_COARSE = 4.0  # a line fit stops after its coarse stage when the misfit is over this
LINE_STOP_FINE = 3.0  # ... or after the fine Gauss–Newton steps over this × the misfit it must
#                       reach to matter (coarse → final measured ≤ 2.7×, fine GN → final ≤ 2.0×
#                       on noisy captures, ≤ 2.7× on the noise-free seed lines; a ray-sampled
#                       line off super-cells, which takes no such steps since stop 80
#                       (LINE_RAYS_FINE_GN), is read where the coarse stage ended) ...
LINE_STOP_FLOOR = 0.02  # ... the coarse stage's limit at least this × LINE_STOP_COARSE: on
#                         noise-free data the coarse model's own ray noise dominates its misfit
#                         (0.01-0.03), not the data's (the fine model is the final one)
SIGMA_FLOOR_REL = 3e-4  # added in quadrature to the fit's σ of a distance: the share of the
# calibration and the model that the statistical σ leaves out (bright blurs: σ 0.002-0.003 %,
# error 0.014-0.026 %). Chosen on the 108 single sources of benchmarks/focus_grid.py (3σ:
# 92 → 108), checked on the independent renderer's (2σ: 29 → 38 of 40; docs/distance.md)
POLISH_MAX_GAIN = 0.9  # the polish lowers a point's misfit by at most this share (82 % seen)
POLISH_GAIN_SAFETY = 5.0  # ... and its misfit² by at most this × a linear step's prediction
POLISH_GAIN_MIN = 0.1  # ... or by this share of it, whichever is more (docs/distance.md,
#                         "The polish's reach": measured up to 1.9 × the prediction where it
#                         matters, 4.3 × where it is under 0.005)
POLISH_UNSETTLED = 0.5  # ... unless that step removes over this share of the misfit²: the fine
#                         fit is far from its own minimum, and there is no floor (a point is
#                         polished before a line is tried; lines fitted as points: at most 5 %
#                         on the focus grid; an F/2 point at 75 % of the field left 98 %, and
#                         its polish 98.7 %: docs/distance.md, "An unsettled point is polished
#                         before a line (stop 60)")
POOR_FIT = 0.12  # best misfit over this: neither model explains the data (status poor-fit)
# The distance profile (docs/distance.md, "Blurs of a few lenslets"). A blur over a 2×2 block
# of lenslets splits the pupil into four parts whose shapes fix only the ratio of the image
# point's lateral offset from the cell borders to its defocus: along that ridge the misfit is
# flat and the Jacobian's σ (taken at one point of it) is meaningless.
PROFILE_LENSLETS = 16  # blurs lighting at most this many lenslets get the profile check
PROFILE_MAX_LOG = 0.7  # a side not bounded within ×2 (log distance 0.7): no distance
PROFILE_RIDGE_LOG = 0.1  # a 10 % step costing less than PROFILE_RIDGE_RISE × the model's
PROFILE_RIDGE_RISE = 5.0  # systematic misfit² (≤ PROFILE_FLOOR²): a ridge, no distance
PROFILE_FLOOR = 0.001  # relative misfit of the exact model on bright far sources (0.0006-7)
PROFILE_GN_STEPS = 2  # lateral Gauss–Newton steps at each trial distance (fixed Jacobian)
PROFILE_START = 2.0  # the first trial step, in units of the Jacobian's σ
CELL_MAP_TOLERANCE = 0.01  # a point's polynomial map off its ring's traced rays by at most this
#                            (pitches), or the cells do not apply
LINE_FAR_POINT_START = True  # a line whose point fit ran out to the far bound starts from
#                              the scan alone (docs/distance.md, "No line start at the far
#                              bound (stop 59)")
CELLS_FOLD_FIRST = True  # a map that folds is refused by its Jacobian's sign before the
#                          cells are sampled (docs/distance.md, "A folded map refused
#                          before its samples (stop 59)")
CELL_AREA_TOLERANCE = 0.005  # a point's samples' pupil area within this share of π: one to one
CELLS_WHOLE = True  # the cells a point lights whole are integrated by a rule (a rectangular
#                     lattice's: 2 × 2 Gauss; a hexagonal one's: a ring of six), the rest
#                     sampled (kernels.cell_centres; docs/distance.md, "Cells integrated
#                     whole (stop 43)", "Whole hexagonal cells (stop 45)")
CELLS_WHOLE_HEX_MIN_N = 3  # ... on a hexagonal lattice by the ring of six from this n on (n = 2:
#                            4 samples a cell, fewer than the ring's 6; CELLS_COARSE_HEX below)
CELLS_COARSE_HEX = True  # a hexagonal lattice's coarse models (n < CELLS_WHOLE_HEX_MIN_N) integrate
#                          the cells whole too, by three of the ring's points and one
#                          parallelogram (CellRule.coarse): n = 2's samples left 4.7e-2 of
#                          a large blur's moments, this 7.3e-3, at 0.21 against 0.23 ms a
#                          point (docs/distance.md, "A coarse rule for the hexagonal lattice
#                          (stop 46)")
CELL_HEX_REGULAR = 0.02  # ... whose six nearest neighbours' distances agree within this share
#                          (the ring is the regular hexagon's, through the lattice's affine map)
CELLS_RIM = True  # on a hexagonal lattice the cells the pupil's rim cuts too, each over its
#                   part inside it (the rim's image a line across the cell: kernels._rim_cut;
#                   docs/distance.md, "Rim cells cut by the rim's line (stop 46)"); not on
#                   a rectangular one, whose rim cells n = 3 samples cheaply and closer
CELL_SHARE = 0.9  # a cell sample's share across a cell border: over this × its sub-cell's width
RAY_SHARE_RICHARDSON = True  # a ray sample's share across a cell border by two boxes whose
#                              combination has no second moment (sampling.ray_share); one box
#                              widened each footprint by its variance, which put the fine line
#                              model's distance −0.38 % off far behind focus (docs/distance.md,
#                              "Ray shares without the box's variance (stop 53)")
PIXEL_POLISH = True  # measure_lenslet refits a point whose answer is less certain than
#                      PIXEL_POLISH_ABOVE on its lit pixels (:func:`pixel_polish`): behind
#                      focus a dim source's 2-4 px spots carry 3-5 × the distance information
#                      its four moments a lenslet keep (docs/distance.md, "The lit pixels of an
#                      uncertain point (stop 63)")
PIXEL_POLISH_ABOVE = 0.003  # ... its relative σ (the floor SIGMA_FLOOR_REL included) over this,
#                             and, with a tolerance, not accepted
PIXEL_RAYS = 20000  # rays of the pixel model (40 000: the same accuracy over 1 440 regions,
#                     z² ×0.99-1.04 on two halves, 10 % more CPU; docs/distance.md, stop 63)
PIXEL_TURNS = 1  # ... and the minima of this many turned samples averaged with its own (3: the
#                  same accuracy over 720 regions, 2.5 × the cost; docs/distance.md, stop 65)
PIXEL_WINDOW_RAYS = 20000  # ... of the model that finds the lit pixels at the lenslet answer
PIXEL_WINDOW_SHARE = 0.02  # a pixel is lit where that model puts over this × its brightest
#                            pixel's light on it ...
PIXEL_WINDOW_GROW = 1  # ... and so are its neighbours this many pixels out (8-connected)
PIXEL_MIN_PIXELS = 20  # fewer lit pixels: no pixel polish
PIXEL_STRAY_Z = 5.0  # a pixel brighter than the model by over this × its noise where the steps
#                      have come near the minimum holds light not this source's (a
#                      neighbour's halo): left out ...
PIXEL_MAX_STRAY = 0.1  # ... but over this share of the lit pixels stray: no pixel answer
PIXEL_ITERATIONS = 8  # Gauss–Newton steps, at most (each halved up to PIXEL_HALVINGS times)
PIXEL_HALVINGS = 4
PIXEL_REJACOBIAN_LOG = 0.005  # the Jacobian is taken again after a step over this (log distance)
PIXEL_SETTLE_LOG = 2e-5  # ... and the steps end on one under this
PIXEL_MIN_TRIAL_SIGMA = 0.1  # ... and no step (nor halving of a failed one) is tried whose
#                              distance moves under this × the fit's σ there: at the minimum
#                              of the fixed ray sample such steps fail, five traces each
PIXEL_GAIN_LIGHT = 10.0  # the pixels' own gain from those lit over this × the read σ ...
PIXEL_GAIN_PIXELS = 30  # ... at least this many of them (else the capture's gain)
CHI2_1_MEDIAN = NORMAL_MAD_SCALE ** -2  # the median of χ² with one degree of freedom, Φ⁻¹(¾)²
PIXEL_AGREE_SIGMAS = 10.0  # a pixel answer further from the lenslet one than this × its σ is
#                           not taken (:func:`_agrees`)
PIXEL_POINT_CHI2 = 10.0  # the pixels' χ²/dof at the capture's own (upper-bound) noise over
#                         this: no point explains them (a line is tried, else poor-fit). Point
#                         blurs reach 0.47 (dim, refitted), 4.8 (bright, refitted to test);
#                         dim lines 73-106
PIXEL_MAX_CHI2 = 4.0  # χ²/dof over this: the pixel model does not explain the pixels (the
#                       lenslet answer stands)
KERNEL = "compiled"  # rays → moments: lfcam.measure.kernels; "numpy" = the reference chain
OTHERS_EXCLUDED = True  # measure_lenslet leaves its ``others``' lenslets out of the box
LINE_WEIGHTED_SUMS = True  # a ray-sampled line's weighted sums added in the deposit, not from
#                            each point's own moments (LensletModel.simulate_weighted)
TRACE_DEPOSIT_FUSED = True  # the compiled ray models trace and deposit a point's rays in one
#                             pass (kernels.trace_deposit_moments; False: the two calls, the
#                             same sums bit for bit: docs/distance.md, "The trace and the
#                             deposit in one pass (stop 59)")
_LATTICES = ObjectCache(8)
_RULES = ObjectCache(8)
_PEDESTAL = ObjectCache(1)
_EMPTY_BOX = np.array([1.0, 0.0, 1.0, 0.0])  # cell_samples: no sample for this point
_NO_POLYGON = np.zeros((0, 2))  # cell_centres without the rim's cut cells
_ONE_BOX = np.empty(0)  # deposit_moments' per-ray box sizes where one is for all rays
_NO_WEIGHTS = np.empty(0)  # trace_deposit_moments' second sums: none


def lattice_of(geom: Geometry, pitch_mm: float) -> LocalLattice | None:
    """The exact lenslet-cell lookup of a geometry (cached per geometry object)."""
    return _LATTICES.get(geom, lambda: LocalLattice.fit(geom.lens_centres_mm, pitch_mm))


def keep_lattice(geom: Geometry, lattice: LocalLattice | None) -> None:
    """Remember ``lattice`` (:func:`lattice_of`'s, computed elsewhere: a region worker gets
    its parent's) for ``geom``."""
    _LATTICES.get(geom, lambda: lattice)


@dataclass
class LensletMoments:
    """A region's lenslets and their four moments (module docstring): the data's, or, with
    ``data`` zero, the layout a model fills (:class:`LensletModel` writes its moments in this
    order)."""

    box: tuple[int, int, int, int]
    labels: np.ndarray  # (h, w) compact lenslet index in the box, −1 none
    ids: np.ndarray  # (K,) geometry lenslet index of each compact index
    centres_px: np.ndarray  # (K, 2) micro-image centres
    data: np.ndarray  # (K, 4)
    norm: float
    noise_sums: tuple[float, float] = (math.nan, math.nan)  # noise.moment_noise_sums


def _moments_of(centres_px, pitch_px, x_px, y_px, w, k, group=None, groups=1):
    """Four moments per compact lenslet ``k`` from samples at pixel (x, y) with weight w;
    with ``group`` (one per sample), ``groups`` stacked sets: (groups·K, 4)."""
    n = len(centres_px)
    dx = (x_px - centres_px[k, 0]) / pitch_px
    dy = (y_px - centres_px[k, 1]) / pitch_px
    bins = k if group is None else group * n + k
    n = n * groups
    out = np.empty((n, 4))
    out[:, 0] = np.bincount(bins, w, minlength=n)
    out[:, 1] = np.bincount(bins, w * dx, minlength=n)
    out[:, 2] = np.bincount(bins, w * dy, minlength=n)
    out[:, 3] = np.bincount(bins, w * (dx * dx + dy * dy), minlength=n)
    return out


def pedestal(image: np.ndarray) -> float:
    """Mean level of the pixels that see no source: a sensor that clips its noise at zero
    (unsigned raws) leaves a positive mean of ~0.4 σ in the dark, which the moments would read
    as light. A sample of the frame, values above median + 5 σ left out (σ from the upper
    quartile, which clipping does not move)."""
    def level() -> float:
        sample = image[:: max(1, image.shape[0] // 256), :: max(1, image.shape[1] // 256)]
        med, upper = np.percentile(sample, [50.0, 75.0])
        # the upper quartile keeps its place when the noise below zero is clipped
        sig = max(float(upper - med) / 0.6745, 1e-12)
        dark = sample[sample <= med + 5.0 * sig]
        return float(dark.mean()) if dark.size else 0.0

    return _PEDESTAL.get(image, level)


def data_moments(geom: Geometry, image: np.ndarray, box: tuple[int, int, int, int],
                 kernel: str | None = None, exclude: np.ndarray | None = None) -> LensletMoments:
    """Moments of the data over the lenslets whose pixels lie in ``box`` (the dark pedestal
    removed, :func:`pedestal`), and their noise sums. ``kernel``: "compiled"
    (:func:`lfcam.measure.kernels.box_moments`, one pass) or "numpy" (the reference);
    default :data:`KERNEL`. ``exclude``: lenslet indices left out of the box (the other
    regions' lenslets: a neighbouring blur's light is not this source's). The models read
    the same compact map, so they leave them out too (docs/distance.md, "Other regions'
    lenslets left out of a box (stop 60)")."""
    x0, y0, x1, y1 = box
    lab = geom.lmap.labels[y0:y1, x0:x1]
    drop = np.zeros(0, dtype=bool)  # a flag per lenslet left out (none: empty)
    if exclude is not None and len(exclude):
        drop = np.zeros(geom.lmap.count + 1, dtype=bool)  # (label −1 reads the last: kept)
        drop[exclude] = True
    ped = pedestal(image)
    if (KERNEL if kernel is None else kernel) == "compiled":
        from lfcam.measure.kernels import box_moments  # numba

        # the box's slices as they lie (no copy); other types than these as float64 / int32
        view = image[y0:y1, x0:x1]
        if view.dtype not in (np.float32, np.float64):
            view = view.astype(np.float64)
        ids, compact, m, s0, s1 = box_moments(
            lab if lab.dtype == np.int32 else lab.astype(np.int32), view, drop,
            np.ascontiguousarray(geom.lmap.centres_px, dtype=np.float64), int(x0), int(y0),
            float(geom.pitch_px), float(ped), int(geom.lmap.count))
        return LensletMoments(box, compact, ids, geom.lmap.centres_px[ids], m,
                              float(np.sqrt((m * m).sum())), (s0, s1))
    if drop.size:
        lab = np.where(drop[lab], -1, lab)
    keep = lab >= 0
    present = np.bincount(lab[keep], minlength=geom.lmap.count) > 0
    ids = np.flatnonzero(present)
    index = np.full(geom.lmap.count + 1, -1, dtype=np.int64)
    index[ids] = np.arange(len(ids))
    compact = index[lab]  # label −1 reads the last entry: −1
    inv = compact[keep]
    yy, xx = np.nonzero(keep)
    cen = geom.lmap.centres_px[ids]
    v = np.asarray(image[y0:y1, x0:x1], dtype=np.float64)[keep] - ped
    m = _moments_of(cen, geom.pitch_px, xx + x0, yy + y0, v, inv)
    dx = (xx + x0 - cen[inv, 0]) / geom.pitch_px
    dy = (yy + y0 - cen[inv, 1]) / geom.pitch_px
    return LensletMoments(box, compact, ids, cen, m, float(np.sqrt((m * m).sum())),
                          moment_noise_sums(dx, dy, v))


_RAY_COUNTS: list[list[int]] = []  # the open counting_rays blocks' counts


@contextmanager
def counting_rays() -> Iterator[list[int]]:
    """Count the rays every :class:`LensletModel` evaluation inside the block traces (its
    points × its pupil sample): yields a one-item list holding the count so far. A cost that
    does not depend on the machine's load, for benchmarks and tests
    (``benchmarks/overlapping_blurs.py --refits``)."""
    count = [0]
    _RAY_COUNTS.append(count)
    try:
        yield count
    finally:
        _RAY_COUNTS.remove(count)


@dataclass(frozen=True)
class CellBins:
    """A region's lenslets grouped into super-cells of ``k`` × ``k`` lattice cells (the
    lattice's own indices floor-divided by ``k``), and the data's moments summed over each: a
    residual on them (:meth:`LensletModel.residual_of`) is the same fit on ``k²`` × fewer
    cells, whose sums a model with ``k²`` × fewer rays samples as well as it samples a
    lenslet's. The four moments are sums (each relative to its own lenslet's centre), so a
    super-cell's are its lenslets' added."""

    index: np.ndarray  # (K,) each lenslet's super-cell
    count: int  # super-cells
    data: np.ndarray  # (count, 4) the data's moments, summed
    norm: float  # their norm

    @classmethod
    def of(cls, geom: Geometry, mom: LensletMoments, lattice: LocalLattice,
           k: int) -> CellBins:
        """The super-cells of ``k`` × ``k`` cells of ``lattice`` over ``mom``'s lenslets."""
        c = geom.lens_centres_mm[mom.ids]
        ij = np.column_stack(lattice.cell_indices(c[:, 0], c[:, 1]))
        blocks, index = np.unique(np.floor_divide(ij, k), axis=0, return_inverse=True)
        index = index.ravel()
        count = len(blocks)
        data = _bin_sums(mom.data, index, count)
        return cls(index, count, data, float(np.sqrt((data * data).sum())))


def _bin_sums(m: np.ndarray, index: np.ndarray, count: int) -> np.ndarray:
    """(K, 4) moments summed per super-cell ``index``: (count, 4)."""
    out = np.empty((count, 4))
    for c in range(4):
        out[:, c] = np.bincount(index, m[:, c], minlength=count)
    return out


class LensletModel:
    """Forward model of a region's lenslet moments for point (or line) sources."""

    def __init__(self, profile: CameraProfile, geom: Geometry, mom: LensletMoments, n_rays: int,
                 phase: float = 0.0, kernel: str | None = None, turn_every: int = 0,
                 cells: int = 0):
        from lfcam.measure.kernels import keep_large_buffers

        keep_large_buffers()  # (once a process) its evaluations' large temporaries reused
        self.profile, self.geom, self.mom = profile, geom, mom
        # cells = n > 0: each point's pupil sample is the preimage of the centres of the n × n
        # sub-cells of every lattice cell (n² samples a cell, ``n_rays`` and ``phase`` unused;
        # the compiled kernel only): the samples stay where they are on the MLA as the source
        # moves, so no sample crosses a cell border and the Jacobian by differences is not
        # the sample's noise (docs/distance.md, "Samples fixed on the lenslet cells")
        self.cells = int(cells)
        self.folded = False  # cells did not apply (:meth:`invertible`): ray-sampled from then on
        # turn_every = c > 0: the k-th point of each run of c stacked points (a line's k-th
        # point, in every set of a Jacobian or a scan) has its pupil sample turned by
        # 2πk / c, so that the points' sampling errors cancel instead of adding up
        # (docs/distance.md, "A line's points, each with its own turn of the pupil sample")
        self.turn_every = int(turn_every)
        # "compiled" (lfcam.measure.kernels) or "numpy" (the reference it is tested against)
        self.kernel = KERNEL if kernel is None else kernel
        lens = profile.main_lens
        half = 0.5 * lens.pupil_diameter_mm
        u, v = vogel_disc(n_rays, phase)
        self.rx, self.ry = u * half, v * half
        self.spacing = lens.pupil_diameter_mm * math.sqrt(math.pi / (4.0 * n_rays))
        # sensor-plane spacing of the rays (px): the pupil sample spacing, imaged by a lenslet
        mag = (profile.mla.focal_length_mm / (geom.d_in_mm - lens.exit_pupil_z_mm)
               / profile.sensor.pixel_pitch_mm)
        self.s_px = min(0.9, self.spacing * mag)
        self.lattice = lattice_of(geom, profile.mla.pitch_mm)
        self.cell_shape = None if self.lattice is None else _cell_shape(self.lattice)
        # the cells a point lights whole integrated by a rule (cell_rule: None on a lattice
        # that is neither rectangular nor nearly regular hexagonal)
        self.rule = None if self.lattice is None else _RULES.get(
            self.lattice, lambda: cell_rule(self.lattice))
        if (self.rule is not None and self.rule.coarse is not None and CELLS_COARSE_HEX
                and self.cells < CELLS_WHOLE_HEX_MIN_N):
            self.rule = self.rule.coarse  # (a hexagonal lattice's coarse models: three points)
        self.whole = self.whole_at(self.cells)
        self.packed = None  # the lens as the compiled trace reads it (on first use)
        self.evaluations = 0

    def whole_at(self, n: int) -> bool:
        """Whether a model on the cells with ``n`` × ``n`` samples a cell integrates the cells
        a point lights whole (:data:`CELLS_WHOLE`, :func:`cell_rule`)."""
        return bool(CELLS_WHOLE and self.rule is not None
                    and (self.rule.rect or n >= CELLS_WHOLE_HEX_MIN_N or CELLS_COARSE_HEX))

    def fine_cells(self) -> int:
        """The fine stage's n on the cells: :data:`LINE_CELLS_FINE_WHOLE` where a rectangular
        lattice's whole cells are integrated, else :data:`LINE_CELLS_FINE` (a hexagonal
        lattice's n = 3 left its rim cells' samples too coarse, whole cells or not:
        docs/distance.md, "Whole hexagonal cells (stop 45)"; with the rim's cells cut, stop
        46, n there sets only the cells still sampled, whose pupil patch is over
        ``kernels.CELL_WHOLE_MAX_PATCH``)."""
        rect = self.rule is not None and self.rule.rect
        return (LINE_CELLS_FINE_WHOLE if rect and self.whole_at(LINE_CELLS_FINE_WHOLE)
                else LINE_CELLS_FINE)

    def simulate(self, sources: np.ndarray) -> np.ndarray:
        """(K, 4) moments of unit-intensity source point(s) ``(3,)`` or ``(M, 3)``.

        Each ray stands for a patch of the pupil; it is spread as a box of the local ray
        spacing across the lenslet-cell border it lies near (MLA plane) and across the pixel
        border (sensor). With the box shrunk to nothing this is the renderer's binning; with it,
        the moments are continuous (piecewise linear) in the source position, so that
        finite-difference Jacobians with small steps are meaningful.
        """
        self.evaluations += 1
        with np.errstate(over="ignore", invalid="ignore"):  # rays that miss: ok = False
            return self._simulate(sources)

    def simulate_each(self, sources: np.ndarray) -> np.ndarray:
        """(M, K, 4) moments of each of ``M`` sources separately, in one pass."""
        self.evaluations += 1
        src = np.atleast_2d(sources)
        with np.errstate(over="ignore", invalid="ignore"):
            return self._simulate(src, np.arange(len(src)), len(src)).reshape(len(src), -1, 4)

    def simulate_sets(self, sets: list, evaluations: int | None = None) -> np.ndarray:
        """(S, K, 4) moments of ``S`` source sets (each a point ``(3,)`` or points ``(M, 3)``),
        in one trace: each set's moments equal :meth:`simulate` of that set (the same sums in
        the same order), without the per-call overhead. Counts ``S`` evaluations, or
        ``evaluations`` (sets that are parts of fewer sources' evaluations)."""
        pts = [np.atleast_2d(np.asarray(v, dtype=np.float64)) for v in sets]
        group = np.concatenate([np.full(len(v), g, dtype=np.int64) for g, v in enumerate(pts)])
        return self.simulate_groups(np.concatenate(pts), group, len(pts),
                                    len(pts) if evaluations is None else evaluations)

    def simulate_groups(self, points: np.ndarray, group: np.ndarray, groups: int,
                        evaluations: int) -> np.ndarray:
        """(groups, K, 4) moments of ``points`` (M, 3) summed per ``group`` (M,) (0 …
        ``groups`` − 1, non-decreasing): :meth:`simulate_sets` with the sets already stacked.
        Counts ``evaluations``."""
        self.evaluations += evaluations
        with np.errstate(over="ignore", invalid="ignore"):
            out = self._simulate(np.ascontiguousarray(points, dtype=np.float64), group, groups)
        return out.reshape(groups, -1, 4)

    def simulate_weighted(self, points: np.ndarray, group: np.ndarray, groups: int,
                          weights: np.ndarray, evaluations: int
                          ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`simulate_groups`' (groups, K, 4) moments, and the same sums with each
        point's moments times its ``weights`` (M,): on the rays both in one pass of the
        compiled kernel (no moments of each point apart: 24 points' own moments of a
        2 900-lenslet box took 4.6–4.9 ms against their sum's 3.8, and numpy's sums 0.2–0.3
        ms more; docs/distance.md, "A line's weighted sums in the deposit (stop 75)");
        elsewhere from each point's own, then summed."""
        self.evaluations += evaluations
        pts = np.ascontiguousarray(points, dtype=np.float64)
        w = np.ascontiguousarray(weights, dtype=np.float64)
        with np.errstate(over="ignore", invalid="ignore"):
            if (LINE_WEIGHTED_SUMS and not self.cells and self.kernel == "compiled"
                    and TRACE_DEPOSIT_FUSED):
                out = self._simulate(pts, group, groups, second=w).reshape(2, groups, -1, 4)
                return out[0], out[1]
            each = self._simulate(pts, np.arange(len(pts)), len(pts)).reshape(len(pts), -1, 4)
        sums = np.zeros((2, groups, *each.shape[1:]))
        for g in range(groups):
            mine = group == g
            sums[0, g] = each[mine].sum(0)
            sums[1, g] = np.tensordot(w[mine], each[mine], 1)
        return sums[0], sums[1]

    def turns(self, m: int) -> np.ndarray:
        """(m, 2) cos and sin of each of ``m`` stacked points' pupil-sample turn."""
        out = np.zeros((m, 2))
        out[:, 0] = 1.0
        if self.turn_every > 1:
            a = 2.0 * math.pi / self.turn_every * (np.arange(m) % self.turn_every)
            out[:, 0], out[:, 1] = np.cos(a), np.sin(a)
        return out

    def _simulate(self, sources: np.ndarray, group: np.ndarray | None = None,
                  groups: int = 1, second: np.ndarray | None = None) -> np.ndarray:
        """Moments of ``sources`` summed per ``group`` (one group without it): (groups·K, 4);
        with ``second`` (the compiled rays only, :meth:`simulate_weighted`), then the same
        sums with each point's moments times ``second``: (2·groups·K, 4)."""
        points = np.atleast_2d(sources)
        for count in _RAY_COUNTS:
            count[0] += len(points) * self.rx.size
        if second is not None or (not self.cells and self.kernel == "compiled"):
            return self._simulate_compiled(points, group, groups, second)
        out = np.zeros((groups * len(self.mom.data), 4))
        if self.cells:
            return self._simulate_cells(points, group, groups, out)
        p = self.profile
        lens = p.main_lens
        fx = p.mla.focal_length_mm
        pp = p.sensor.pixel_pitch_mm
        ax, ay = p.sensor.axis_xy_px
        x0, y0 = self.mom.box[:2]
        h, w = self.mom.labels.shape
        s_px = self.s_px
        # each point's aperture points, turned by its own angle (none: the same for all)
        cs = self.turns(len(points))
        rx = cs[:, :1] * self.rx[None, :] - cs[:, 1:] * self.ry[None, :]
        ry = cs[:, 1:] * self.rx[None, :] + cs[:, :1] * self.ry[None, :]
        # every point's rays in one trace (lines: LINE_POINTS points)
        tr = trace_sources_fast(lens, points, rx, ry, self.geom.d_in_mm)
        ok = tr.ok
        if not ok.any():
            return out
        along = lens.rim_z_mm - points[:, 2:3]
        rho2 = (rx - points[:, :1]) ** 2 + (ry - points[:, 1:2]) ** 2
        wt = ((along * along / (rho2 + along * along)) ** 1.5)[ok]
        # MLA-plane ray spacing: each footprint's extent over the pupil's, times the pupil
        # spacing (rays of one point are contiguous: per-point extremes by reduceat)
        rows_ok = np.nonzero(ok)[0]
        x, y = tr.x[ok], tr.y[ok]
        lit, first = np.unique(rows_ok, return_index=True)
        foot = np.zeros(len(points))
        foot[lit] = np.maximum(
            np.maximum.reduceat(x, first) - np.minimum.reduceat(x, first),
            np.maximum.reduceat(y, first) - np.minimum.reduceat(y, first))
        spacing = np.maximum(self.spacing * foot / lens.pupil_diameter_mm, 1e-12)
        sx = fx * tr.dx[ok] / tr.dz[ok]
        sy = fx * tr.dy[ok] / tr.dz[ok]
        gaps = spacing[rows_ok]
        tag = group[rows_ok] if group is not None else np.zeros(rows_ok.size, dtype=np.int64)
        c1x, c1y, c2x, c2y, gap = _two_cells(self.lattice, x, y)
        share = ray_share(gap, gaps, RAY_SHARE_RICHARDSON)
        split = share != 0
        cx = np.concatenate([c1x, c2x[split]])
        cy = np.concatenate([c1y, c2y[split]])
        wt = np.concatenate([wt * (1.0 - share), (wt * share)[split]])
        tag = np.concatenate([tag, tag[split]])
        px = (cx + np.concatenate([sx, sx[split]])) / pp + ax - x0
        py = (cy + np.concatenate([sy, sy[split]])) / pp + ay - y0
        cols, rows, wts_, ray = pixel_boxes(px, py, wt, s_px, with_source=True)
        inside = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
        cols, rows, wts_, ray = cols[inside], rows[inside], wts_[inside], ray[inside]
        k = self.mom.labels[rows, cols]
        known = k >= 0
        return _moments_of(self.mom.centres_px, self.geom.pitch_px, cols[known] + x0,
                           rows[known] + y0, wts_[known], k[known],
                           tag[ray[known]] if group is not None else None, groups)

    def _simulate_compiled(self, points: np.ndarray, group: np.ndarray | None, groups: int,
                           second: np.ndarray | None = None) -> np.ndarray:
        """:meth:`_simulate` through the compiled trace and deposit, in one pass a point
        (:func:`lfcam.measure.kernels.trace_deposit_moments`): the same rays, weights,
        spacings and sums as the trace (``trace_model_rays``) and :meth:`_deposit`.
        ``second``: the kernel's weighted sums as well (the fused kernel's only)."""
        from lfcam.measure.kernels import trace_deposit_moments, trace_model_rays  # numba

        lens = self.profile.main_lens
        pts = np.ascontiguousarray(points, dtype=np.float64)
        lens_args = self._trace_args()
        # the real stop's image on the aperture plane, per point (identity for the singlet)
        rays = (pts, compiled_pupil_maps(lens, pts, self.packed), self.turns(len(pts)),
                self.rx, self.ry, *lens_args)
        if not TRACE_DEPOSIT_FUSED and second is None:  # the two calls (the reference the
            #                                               tests compare with)
            x, y, sx, sy, wt, rows, _, foot = trace_model_rays(*rays)
            if rows.size == 0:
                return np.zeros((groups * len(self.mom.data), 4))
            spacing = np.maximum(self.spacing * foot / lens.pupil_diameter_mm, 1e-12)
            return self._deposit(x, y, sx, sy, wt, rows, spacing, group, groups, len(points),
                                 self.s_px, RAY_SHARE_RICHARDSON)
        return trace_deposit_moments(
            *rays, float(self.spacing), float(lens.pupil_diameter_mm),
            *self._lattice_args(group, groups, len(points)), float(self.s_px), self.mom.labels,
            self.mom.centres_px, float(self.geom.pitch_px), bool(RAY_SHARE_RICHARDSON),
            _NO_WEIGHTS if second is None else second)

    def _trace_args(self) -> tuple:
        """The compiled trace's lens arguments (:func:`lfcam.measure.kernels.trace_model_rays`
        after the aperture points): the packed prescription, its front vertex and rim, the MLA
        plane and the lenslets' focal length."""
        p = self.profile
        lens = p.main_lens
        if self.packed is None:
            self.packed = _packed_lens(lens)
        return (self.packed.table, self.packed.coef, float(lens.front_vertex_z_mm),
                float(lens.rim_z_mm), float(self.geom.d_in_mm), float(p.mla.focal_length_mm))

    def _lattice_args(self, group: np.ndarray | None, groups: int, m: int) -> tuple:
        """The deposits' arguments from ``group`` to the box's corner
        (:func:`lfcam.measure.kernels.deposit_moments`, ``trace_deposit_moments``): each of
        the ``m`` points' group (None: one group), the lattice and its cells' shape, the pixel
        pitch, the sensor axis and the box's corner, each as the kernels' one signature
        takes it (a new one would compile again, ~3 s)."""
        p = self.profile
        if group is None:
            group = np.zeros(m, dtype=np.int64)
        lat = self.lattice
        la, lb, rect = self.cell_shape or _cell_shape(lat)  # (no lattice: fails as before)
        ax, ay = p.sensor.axis_xy_px
        x0, y0 = self.mom.box[:2]
        return (np.asarray(group, dtype=np.int64), int(groups), lat.origin, lat.basis,
                lat.inverse, rect, la, lb, float(p.sensor.pixel_pitch_mm), float(ax),
                float(ay), int(x0), int(y0))

    def _deposit(self, x, y, sx, sy, wt, rows, spacing, group, groups, m,
                 s_px: float | np.ndarray, richardson: bool = False) -> np.ndarray:
        """Moments of traced rays (:func:`lfcam.measure.kernels.deposit_moments`): ray ``r``
        from point ``rows[r]`` of ``m``, whose rays are ``spacing[rows[r]]`` apart on the MLA,
        spread as ``s_px`` boxes on the sensor (an array: ray ``r`` as an ``s_px[r]`` box);
        ``group`` per point (None: one group); ``richardson``: shared across cell borders by
        :func:`~lfcam.measure.sampling.ray_share`'s combination of two boxes (the ray
        samples), else by one box (the samples on the cells)."""
        from lfcam.measure.kernels import deposit_moments  # numba

        each = isinstance(s_px, np.ndarray)  # (the kernel's scalar then unread)
        return deposit_moments(
            x, y, sx, sy, wt, rows.astype(np.int64, copy=False), spacing,
            *self._lattice_args(group, groups, m), 1.0 if each else float(s_px),
            self.mom.labels, self.mom.centres_px, float(self.geom.pitch_px),
            s_px if each else _ONE_BOX, bool(richardson))

    def _cell_samples(self, points: np.ndarray):
        """Each point's pupil samples on the cells (``cells`` > 0), or ``None`` where a point's
        pupil is vignetted or its map from the pupil to the MLA is not one to one (the MLA
        cuts the caustic: in front of focus, near it).

        Each point's map from the unit pupil disc to the MLA is fitted by a polynomial of
        degree :data:`lfcam.measure.kernels.MAP_DEGREE` (the 81 rays of :func:`_cell_ring`;
        0.0005 pitch RMS off the exact trace on a large system-2 blur, where a linear map
        leaves 0.5–2 pitches of spherical aberration and a cubic 0.015), and each point of the
        sub-grid inside the footprint is mapped back to its pupil point
        (:func:`lfcam.measure.kernels.cell_samples`). A map that is one to one takes each
        pupil point to one sub-grid point, so the samples' pupil areas add up to the disc's, π
        (behind focus to 1e-4); where the map folds they do not (0.25–0.95 measured in front
        of a 1 m focus), and :data:`CELL_AREA_TOLERANCE` tells the two apart.

        The cells a point lights whole (:data:`CELLS_WHOLE`) are left out of the samples and
        integrated by a rule (:func:`cell_rule`, :func:`lfcam.measure.kernels.cell_centres`);
        on a hexagonal lattice so are the cells the pupil's rim cuts (:data:`CELLS_RIM`), and
        a point with no other cell left is not sampled at all.

        Returns ``(u, v, w, rows, du, maps, trace_args, whole, (tx, ty))`` (see
        ``cell_samples``; ``whole``: ``cell_centres``'s output, or None).
        """
        from lfcam.measure.kernels import (
            CELL_WHOLE_MARGIN,
            cell_centres,
            cell_samples,
            trace_model_rays,
        )

        p = self.profile
        lens = p.main_lens
        trace_args = self._trace_args()
        half = 0.5 * lens.pupil_diameter_mm
        lat = self.lattice
        if lat is None:
            raise ValueError("cell samples need a lenslet lattice")
        pts = np.ascontiguousarray(points, dtype=np.float64)
        m = len(pts)
        maps = compiled_pupil_maps(lens, pts, self.packed)
        ring, pinv, ring_basis = _cell_ring()
        x, y, sx, sy, _, rows, ray, _ = trace_model_rays(pts, maps, np.tile([1.0, 0.0], (m, 1)),
                                                         ring[:, 0] * half, ring[:, 1] * half,
                                                         *trace_args)
        n = self.cells
        boxes = np.zeros((m, 4))
        if len(rows) != m * len(ring):
            # a vignetted pupil: its cut runs across the cells, and the samples fixed on them
            # that it drops are not the rays it drops (system 1's lines at 80 % of the
            # half-field behind focus: 0.42 / 1.52 % on the cells, 0.31 / 0.68 % ray-sampled)
            return None
        xr, yr = x.reshape(m, -1), y.reshape(m, -1)
        cx = xr @ pinv.T
        cy = yr @ pinv.T
        pitch = math.sqrt(abs(np.linalg.det(lat.basis)))
        off = np.hypot(xr - cx @ ring_basis.T, yr - cy @ ring_basis.T).max()
        if off > CELL_MAP_TOLERANCE * pitch:
            # the polynomial misses the exact map (far off axis: system 1's at 80 % of the
            # half-field by 0.03 pitch; system 2's behind focus on axis by 0.002)
            return None
        if CELLS_FOLD_FIRST:
            # a map whose Jacobian changes sign on the disc folds (the MLA cuts the caustic):
            # its samples' area fails the test below (0.25-0.95 of π), told here before the
            # whole cells' Newton inversions and the samples (~10 ms on a 380 mm line's three
            # calls; the same decisions on the focus grid's 231 lines and 180 points)
            if not _sign_kept(_disc_det(cx, cy)).all():
                return None
        margin = pitch * (1.0 + 1.0 / n)
        boxes[:, 0] = xr.min(axis=1) - margin
        boxes[:, 1] = xr.max(axis=1) + margin
        boxes[:, 2] = yr.min(axis=1) - margin
        boxes[:, 3] = yr.max(axis=1) + margin
        # a disc about the centre ray's landing through the farthest ring ray, and a margin
        reach = np.column_stack([xr[:, 0], yr[:, 0], np.hypot(xr - xr[:, :1],
                                                              yr - yr[:, :1]).max(axis=1)
                                 + margin])
        # Only the cells whose light can reach the region's box are sampled: a sample lands
        # at its cell's centre (or a neighbour's, where it is shared) plus f_x × its slope,
        # whose length is at most the ring's largest (the rim's image), and is spread over
        # a pixel at most. A dim source's blur reaches beyond its box (a scene's 133-lenslet
        # region: 611 cells a point, 285 lenslets in the box: docs/distance.md, "Speed at
        # stop 42"). Where that cuts any point's footprint, the samples' area no longer tells
        # whether the map is one to one: the map itself does (:func:`_one_to_one`, its
        # Jacobian's sign over the disc and its rim's image; until stop 47 an n = 2 sample of
        # the whole footprint, ~1.5 ms for a line's 12 points); an n = 2 model is not cut.
        x0, y0, x1, y1 = self.mom.box
        ax, ay = p.sensor.axis_xy_px
        pp = p.sensor.pixel_pitch_mm
        reach_mm = float(np.hypot(sx, sy).max()) + 1.5 * pitch + 2.0 * pp
        clip = np.array([(x0 - ax) * pp - reach_mm, (x1 - ax) * pp + reach_mm,
                         (y0 - ay) * pp - reach_mm, (y1 - ay) * pp + reach_mm])
        cut = boxes.copy()
        cut[:, 0] = np.maximum(boxes[:, 0], clip[0])
        cut[:, 1] = np.minimum(boxes[:, 1], clip[1])
        cut[:, 2] = np.maximum(boxes[:, 2], clip[2])
        cut[:, 3] = np.minimum(boxes[:, 3], clip[3])
        args = (reach, lat.origin, lat.basis, lat.inverse)
        la, lb, rect = self.cell_shape
        no_skip = (np.zeros((m, 5), dtype=np.int64), np.zeros(1, dtype=np.bool_))
        cut_off = n > 2 and not np.array_equal(cut, boxes)  # (the area test read from the map)
        if cut_off:
            if not _one_to_one(cx, cy).all():
                return None
            boxes = cut
        whole = None
        skip = no_skip
        if self.whole:
            # the cells lit whole: integrated by a rule (cell_rule), their light spread over
            # the landing's linear image of the cell; the others sampled
            rule = self.rule
            rim = CELLS_RIM and not rule.rect
            whole = cell_centres(cx, cy, boxes, *args, CELL_WHOLE_MARGIN, rule.corners,
                                 rule.points, rule.weights, rule.polygon if rim else _NO_POLYGON)
            skip = whole[6:8]
            if rim:
                # a point whose nodes are all whole, cut or dark has nothing left to sample
                boxes = np.where(whole[14][:, None] > 0, boxes, _EMPTY_BOX)
        # (on a hexagonal lattice a sample across a whole cell's border keeps the other
        # cell's share, weighted and placed on its node: (tx, ty))
        u, v, w, srows, du, tx, ty = cell_samples(cx, cy, boxes, *args, n, *skip,
                                                  CELL_SHARE * pitch / n, rect, la, lb)
        if not cut_off:
            area = np.bincount(srows, w, minlength=m).astype(np.float64)  # (no samples: int)
            if whole is not None:
                area += np.bincount(whole[0], whole[5].sum(axis=1), minlength=m)
                area += np.bincount(whole[8], whole[13].sum(axis=1), minlength=m)
            if np.any(np.abs(area / math.pi - 1.0) > CELL_AREA_TOLERANCE):
                return None
        return u, v, w, srows, du, maps, trace_args, whole, (tx, ty)

    def invertible(self, points: np.ndarray) -> bool:
        """Whether every point's whole pupil passes and its map to the MLA is one to one
        (:meth:`_cell_samples`): where samples on the cells apply."""
        with np.errstate(over="ignore", invalid="ignore"):
            return self._cell_samples(np.atleast_2d(points)) is not None

    def _simulate_cells(self, points: np.ndarray, group: np.ndarray | None, groups: int,
                        out: np.ndarray) -> np.ndarray:
        """:meth:`_simulate` with samples fixed on the lenslet cells (``cells`` > 0): the
        pupil points of :meth:`_cell_samples` traced exactly, and deposited as
        :meth:`_simulate_compiled`'s rays, each weighted by the pupil area it stands for.
        Where a pupil is vignetted or a map is not one to one the model is the ray-sampled one
        from then on (``folded``).
        """
        from lfcam.measure.kernels import (
            CELL_SPLIT,
            RIM_PIECE,
            RIM_SIDES,
            RIM_SPLIT,
            cell_landings,
            deposit_cells,
            trace_sample_rays,
        )

        got = None if self.folded else self._cell_samples(points)
        if got is None:
            self.folded = True
            return self._simulate_compiled(points, group, groups)
        u, v, w, srows, _, maps, trace_args, whole, (tx, ty) = got
        p = self.profile
        lens = p.main_lens
        half = 0.5 * lens.pupil_diameter_mm
        lat = self.lattice
        pts = np.ascontiguousarray(points, dtype=np.float64)
        m = len(pts)
        n = self.cells
        pitch = math.sqrt(abs(np.linalg.det(lat.basis)))
        if srows.size:
            # the samples of each point through the lens, each point its own (srows sorted)
            cuts = np.searchsorted(srows, np.arange(m + 1))
            x, y, sx, sy, wt, rows, ray, _ = trace_sample_rays(pts, maps, cuts, u * half,
                                                               v * half, *trace_args)
            if rows.size:
                wt = wt * w[ray]
                if tx.size:
                    # a sample on a whole cell's border keeps only the other cell's share
                    # and lands there alone: placed on that cell's node (cell_samples)
                    moved = np.isfinite(tx[ray])
                    if moved.any():
                        x = np.where(moved, tx[ray], x)
                        y = np.where(moved, ty[ray], y)
                # a sample stands for its sub-cell, which lies in one lattice cell: shared
                # across a border only when its ray lands off its sub-cell's centre, or where
                # a hexagonal cell's border cuts its sub-cell (a rectangular lattice's samples
                # lie exactly half a sub-cell from the borders: 0.9 × that keeps them whole)
                spacing = np.full(m, CELL_SHARE * pitch / n)
                # each sample spread as a box of its own pupil area's size on the sensor: one
                # size for all, the mean, left the compressed centre of a large blur behind
                # focus 4-5× farther from a dense sample (docs/distance.md, "The whole cells
                # reach the rim; each sample its own box (stop 44)")
                mag = (p.mla.focal_length_mm / (self.geom.d_in_mm - lens.exit_pupil_z_mm)
                       / p.sensor.pixel_pitch_mm)
                s_ray = np.clip(np.sqrt(w[ray]) * (half * mag), 1e-3, 0.9)
                out = self._deposit(x, y, sx, sy, wt, rows, spacing, group, groups, m, s_ray)
        if whole is None:
            return out
        # the whole cells (their rule's rays traced exactly; a cell's light, their sum, lands
        # about their weighted mean as the linear image of the cell their differences give:
        # kernels.cell_centres, deposit_cells), then the rim's cut cells (the 4-point rule of
        # each one's part inside the rim, spread over the rectangle of its second moments)
        for (rows_c, ci, cj, u4, v4, w4), sides_of, pieces, split in (
                (whole[:6], self.rule.sides, self.rule.pieces,
                 CELL_SPLIT if self.rule.pieces.shape[0] else 1),
                (whole[8:14], RIM_SIDES, RIM_PIECE, RIM_SPLIT)):
            if not rows_c.size:
                continue
            nw = rows_c.size
            cuts = np.searchsorted(rows_c, np.arange(m + 1)) * u4.shape[1]
            _, _, sx, sy, wt, _, ray, _ = trace_sample_rays(pts, maps, cuts, u4.ravel() * half,
                                                            v4.ravel() * half, *trace_args)
            every, weight, lx, ly, sides = cell_landings(ray, wt, sx, sy, w4.ravel(), nw,
                                                         sides_of)
            if not every:
                # a rule's ray stopped inside the lens (a cell lit whole is not): the cells do
                # not apply, as where a pupil is vignetted
                self.folded = True
                return self._simulate_compiled(points, group, groups)
            ax, ay = p.sensor.axis_xy_px
            x0, y0 = self.mom.box[:2]
            deposit_cells(out, rows_c, ci, cj, lx, ly, weight, sides,
                          np.zeros(m, dtype=np.int64) if group is None
                          else np.asarray(group, dtype=np.int64),
                          lat.origin, lat.basis, float(p.sensor.pixel_pitch_mm), float(ax),
                          float(ay), int(x0), int(y0), self.mom.labels, self.mom.centres_px,
                          float(self.geom.pitch_px), pieces, split)
        return out

    def residual(self, sources: np.ndarray) -> np.ndarray:
        """Data minus the best-scaled model moments, over the data's norm."""
        return self.residual_of(self.simulate(sources))

    def residual_of(self, m: np.ndarray, bins: CellBins | None = None) -> np.ndarray:
        """Data minus the best-scaled moments ``m``, over the data's norm; with ``bins``, both
        summed over its super-cells first."""
        data, norm = self.mom.data, self.mom.norm
        if bins is not None:
            m, data, norm = _bin_sums(m, bins.index, bins.count), bins.data, bins.norm
        if least_squares.COMPILED_SUMS:
            from lfcam.measure.kernels import scaled_residual  # numba

            return scaled_residual(np.ascontiguousarray(m, dtype=np.float64),
                                   np.ascontiguousarray(data, dtype=np.float64), float(norm))
        mm = float((m * m).sum())
        a = float((m * data).sum()) / mm if mm > 0 else 0.0
        return ((data - a * m) / norm).ravel()


class _PackedLens(NamedTuple):
    """The main lens as the compiled kernels read it, computed once per model."""

    table: np.ndarray  # kernels.pack_prescription
    coef: np.ndarray
    mapped: bool  # the stop is behind the front surface: aperture points mapped per source
    stop: int  # the stop's surface index
    aim: tuple[float, float, float, float]  # lfcam.optics.raytrace.aim_reference
    z_ap: float  # the aperture plane (prescription frame)
    half: float  # half the pupil diameter


def _packed_lens(lens) -> _PackedLens:
    """The main lens's prescription packed for the compiled trace and aperture maps; aperture
    points are mapped per source when the stop is behind the front surface, as
    :func:`lfcam.optics.trace.trace_sources_fast` does."""
    from lfcam.measure.kernels import pack_prescription
    from lfcam.optics.raytrace import aim_reference

    p = lens.as_prescription
    table, coef = pack_prescription(p)
    mapped = p.stop_index != 0
    return _PackedLens(table, coef, mapped, int(p.stop_index),
                       aim_reference(p) if mapped else (0.0, 0.0, 0.0, 0.0),
                       float(lens.rim_z_mm - lens.front_vertex_z_mm),
                       0.5 * lens.pupil_diameter_mm)


def compiled_pupil_maps(lens, points_mm: np.ndarray, packed: _PackedLens | None = None
                        ) -> np.ndarray:
    """:func:`lfcam.optics.trace.pupil_map` of each source ``points_mm`` (M, 3), with the
    stop-edge rays aimed by :func:`lfcam.measure.kernels.pupil_maps` (the same iteration as
    :func:`lfcam.optics.raytrace.aim_rays`, compiled: ~1.3 ms → ~20 µs a source). ``packed``:
    :func:`_packed_lens` of ``lens``, when the caller has it. (M, 4)."""
    from lfcam.errors import OpticsError
    from lfcam.measure.kernels import pupil_maps

    pk = _packed_lens(lens) if packed is None else packed
    pts = np.atleast_2d(np.asarray(points_mm, dtype=np.float64))
    out = np.tile([0.0, 0.0, 1.0, 1.0], (len(pts), 1))
    if not pk.mapped:
        return out
    src = pts - [0.0, 0.0, lens.front_vertex_z_mm]
    good = np.isfinite(src).all(axis=1)  # pupil_map: the identity for a source that is not
    if not good.any():
        return out
    z_ref, r_ep, stop_sd, z_start = pk.aim
    if np.any(src[good, 2] >= z_start):
        raise OpticsError(f"object points must lie in front of the lens (z < {z_start:.4g} mm "
                          "in the front-vertex frame)")
    # a pupil plane through the source cannot parametrise rays (aim_rays' rule)
    z_refs = np.where(np.isclose(z_ref, src[good, 2]), z_start + 0.5, z_ref)
    out[good] = pupil_maps(np.ascontiguousarray(src[good]), z_refs, pk.table, pk.coef,
                           pk.stop, stop_sd, r_ep, pk.z_ap, pk.half)
    return out


def _map_powers(degree: int | None = None) -> list[tuple[int, int]]:
    """The powers ``(i, j)`` of the terms ``u^i v^j`` of :func:`lfcam.measure.kernels._map2`'s
    polynomials, in its order (``k = i + j`` = 0 … degree, then ``i`` = 0 … k); ``degree``
    (default :data:`lfcam.measure.kernels.MAP_DEGREE`): another degree's."""
    from lfcam.measure.kernels import MAP_DEGREE

    d = MAP_DEGREE if degree is None else degree
    return [(i, k - i) for k in range(d + 1) for i in range(k + 1)]


def _map_basis(u: np.ndarray, v: np.ndarray, degree: int | None = None) -> np.ndarray:
    """Terms of :func:`lfcam.measure.kernels._map2` at pupil points (u, v): (n, terms);
    ``degree``: the same order of terms for a polynomial of another degree
    (:func:`_map_powers`)."""
    return np.column_stack([u ** i * v ** j for i, j in _map_powers(degree)])


_CELL_RING: list = []


def _cell_ring() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pupil points (unit disc) a cell-sampled model traces to fit each point's
    polynomial map (centre and rings at 0.25 … 1.0: 81 rays), the fit's pseudo-inverse and
    the polynomial's terms at those points."""
    if not _CELL_RING:
        pts = [(0.0, 0.0)]
        for r, k in ((0.25, 8), (0.5, 12), (0.7, 16), (0.87, 20), (1.0, 24)):
            a = 2.0 * np.pi * (np.arange(k) + 0.5 * (r > 0.5)) / k
            pts += list(zip(r * np.cos(a), r * np.sin(a), strict=True))
        ring = np.array(pts)
        basis = _map_basis(ring[:, 0], ring[:, 1])
        _CELL_RING.append((ring, np.linalg.pinv(basis), basis))
    return _CELL_RING[0]


_FOLD_GRID: list = []
FOLD_RADII = (0.0, 0.25, 0.5, 0.7, 0.8, 0.87, 0.92, 0.96, 0.98, 1.0)  # _one_to_one's rings
FOLD_ANGLES = 64  # ... and points on each (and on the rim)
FOLD_MIN_DET_RATIO = 0.03  # ... and the map's smallest |det| over them at least this × its
#                            largest (system 1 and 2, 250-6000 mm at 0-80 % of the field: at
#                            0.03 or more the n = 2 samples' area was within 1.4 % of π, and
#                            every map whose area passed CELL_AREA_TOLERANCE had 0.015 or more)


def _fold_grid() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The polynomial map's terms' partial derivatives ∂/∂u, ∂/∂v at :func:`_one_to_one`'s
    pupil points (rings :data:`FOLD_RADII`, :data:`FOLD_ANGLES` points each), and the terms
    at the rim's points."""
    if not _FOLD_GRID:
        a = 2.0 * np.pi * np.arange(FOLD_ANGLES) / FOLD_ANGLES
        r = np.repeat(np.asarray(FOLD_RADII), FOLD_ANGLES)
        u, v = r * np.tile(np.cos(a), len(FOLD_RADII)), r * np.tile(np.sin(a), len(FOLD_RADII))
        pows = _map_powers()
        du = np.column_stack([i * u ** max(i - 1, 0) * v ** j for i, j in pows])
        dv = np.column_stack([j * u ** i * v ** max(j - 1, 0) for i, j in pows])
        _FOLD_GRID.append((du, dv, _map_basis(np.cos(a), np.sin(a))))
    return _FOLD_GRID[0]


def _disc_det(cx: np.ndarray, cy: np.ndarray) -> np.ndarray:
    """(M, G): each point's polynomial map's Jacobian determinant on :func:`_fold_grid`'s
    rings (the first: the disc's centre)."""
    du, dv, _ = _fold_grid()
    return (cx @ du.T) * (cy @ dv.T) - (cx @ dv.T) * (cy @ du.T)


def _sign_kept(det: np.ndarray) -> np.ndarray:
    """(M,): whether each point's determinant (:func:`_disc_det`) keeps the sign it has at
    the disc's centre on every ring: a map whose determinant changes sign folds."""
    return np.all(det * det[:, :1] > 0.0, axis=1)


def _one_to_one(cx: np.ndarray, cy: np.ndarray) -> np.ndarray:
    """Whether each point's polynomial pupil → MLA map (``cx``, ``cy`` (M, terms):
    :func:`_map_basis`'s) is one to one on the unit disc, and resolved by the cells: its
    Jacobian determinant keeps one sign over the disc (rings :data:`FOLD_RADII`) and the
    rim's image winds once about the centre's image, its angle monotonic. A map with a
    Jacobian that never vanishes on a disc and a rim whose image is a simple closed curve is
    one to one; where the MLA cuts the caustic (in front of focus, near it) the Jacobian
    changes sign inside the rim. Near the caustic it nearly vanishes: a map whose smallest
    |det| is under :data:`FOLD_MIN_DET_RATIO` of its largest squeezes part of the pupil
    into less than the cells resolve, and fails too. (M,)."""
    det = _disc_det(cx, cy)
    ok = _sign_kept(det)
    size = np.abs(det)
    ok &= size.min(axis=1) >= FOLD_MIN_DET_RATIO * size.max(axis=1)
    rim = _fold_grid()[2]
    z = (cx @ rim.T - cx[:, :1]) + 1j * (cy @ rim.T - cy[:, :1])  # the rim about the centre
    turn = np.angle(np.roll(z, -1, axis=1) / z)  # each step's turn, the loop closed
    winds = np.all(turn > 0.0, axis=1) | np.all(turn < 0.0, axis=1)
    return ok & winds


def _cell_shape(lattice: LocalLattice) -> tuple[float, float, bool]:
    """Lengths of the lattice's two basis vectors and whether its cells are rectangular (a
    shear below 1e-4 moves their corners by < 1e-4 pitch)."""
    b = lattice.basis
    la, lb = float(np.hypot(*b[:, 0])), float(np.hypot(*b[:, 1]))
    return la, lb, bool(abs(b[:, 0] @ b[:, 1]) < 1e-4 * la * lb)


class CellRule(NamedTuple):
    """A lattice cell's corners and the quadrature rule that integrates a point's light over a
    cell it lights whole (:func:`lfcam.measure.kernels.cell_centres`), all as offsets from
    the cell's node on the MLA (mm)."""

    rect: bool  # the lattice's cells are rectangles (else hexagons)
    corners: np.ndarray  # (C, 2): the cell is the polygon of ±these
    points: np.ndarray  # (K, 2): the rule's points
    weights: np.ndarray  # (K,): their shares of the cell's area (sum 1)
    sides: np.ndarray  # (K, 2): each point's landing's coefficient in the two sides of the
    #                    parallelogram a cell's light is spread over (kernels.cell_landings;
    #                    a hexagonal cell: in the landing's linear map's columns, ∂/∂x, ∂/∂y)
    pieces: np.ndarray  # (P, 3, 2): the parallelograms a hexagonal cell's light is spread
    #                     over, each's centre and two sides (none on a rectangular lattice)
    polygon: np.ndarray  # (V, 2): the cell's corners in counter-clockwise order
    coarse: CellRule | None = None  # a hexagonal lattice's rule for its coarse models
    #                                 (n < CELLS_WHOLE_HEX_MIN_N): three points, one
    #                                 parallelogram (pieces empty)


def cell_rule(lattice: LocalLattice) -> CellRule | None:
    """The whole cells' quadrature rule of a lattice.

    A rectangular lattice's cell ``[−½, ½]·b₁ + [−½, ½]·b₂`` takes the 2 × 2 Gauss–Legendre
    rule (``± g·b₁ ± g·b₂``, g = 1/(2√3)) and its light is spread over the landing's linear
    image of the cell (the sides' coefficients ``±1/(4g)``: the differences across it).

    A hexagonal lattice's cell is the hexagon of the points nearest its node (Voronoi). On
    the regular lattice of pitch L (neighbours at 60° steps) its corners lie at radius R =
    L/√3 halfway between neighbours, and six equal weights on a ring at radius R·√(5/12)
    toward them integrate every polynomial up to degree 3 (the ring's second moment is the
    hexagon's 5R²/12 a unit area; odd ones and the fourth-degree anisotropic ones vanish
    by symmetry): the Gauss rule's degree on six rays, three fewer than n = 3's samples. The
    lattice's own is the regular one through its affine map ``[b₁ b₂][e₁ e₂]⁻¹``, as are the
    corners; its six nearest neighbours must agree within :data:`CELL_HEX_REGULAR`, so that
    the affine hexagon is the nearest-node cell the deposit shares samples by. A hexagon's
    light is spread over its image by the landing's linear map (its least-squares fit over
    the ring): three parallelograms, a third of the light each (``pieces``). One
    parallelogram of the hexagon's second moments put a rim cell's light in its own
    micro-image where the label's border cuts its landing by 61 % against the rays' 71 %
    (docs/distance.md, "Whole hexagonal cells (stop 45)").
    ``None`` on any other lattice: its cells are sampled.
    """
    from lfcam.measure.kernels import CELL_GAUSS_2 as g  # numba

    b = lattice.basis
    b1, b2 = b[:, 0], b[:, 1]
    if _cell_shape(lattice)[2]:
        signs = np.array([[2.0 * (q >> 1) - 1.0, 2.0 * (q & 1) - 1.0] for q in range(4)])
        points = np.array([[g * (s1 * b[0, 0] + s2 * b[0, 1]), g * (s1 * b[1, 0] + s2 * b[1, 1])]
                           for s1, s2 in signs])
        corners = np.array([0.5 * (b1 + b2), 0.5 * (b1 - b2)])
        return CellRule(True, corners, points, np.full(4, 0.25), signs / (4.0 * g),
                        np.zeros((0, 3, 2)),
                        _counter_clockwise(np.array([corners[0], -corners[1], -corners[0],
                                                     corners[1]])))
    vecs = np.array([i * b1 + j * b2 for i in range(-2, 3) for j in range(-2, 3)
                     if (i, j) != (0, 0)])
    length = np.hypot(vecs[:, 0], vecs[:, 1])
    order = np.argsort(length, kind="stable")
    near, near_len = vecs[order[:6]], length[order[:6]]
    if near_len.max() > (1.0 + CELL_HEX_REGULAR) * near_len.min() or length[order[6]] < (
            1.5 * near_len.max()):
        return None
    near = near[np.argsort(np.arctan2(near[:, 1], near[:, 0]))]
    # the lattice's affine map of the regular one (pitch 1, neighbours at 0°, 60°, …)
    e = np.array([[1.0, 0.5], [0.0, math.sqrt(3.0) / 2.0]])
    a = np.column_stack([near[0], near[1]]) @ np.linalg.inv(e)
    ang = np.radians(30.0 + 60.0 * np.arange(6))
    radius = 1.0 / math.sqrt(3.0)
    verts = radius * np.column_stack([np.cos(ang), np.sin(ang)])
    points = (math.sqrt(5.0 / 12.0) * verts) @ a.T
    corners = verts @ a.T
    # the hexagon is three parallelograms from its node: corners 0 and 2, 2 and 4, 4 and 0
    pieces = np.array([[(corners[k] + corners[(k + 2) % 6]) / 2.0, corners[k],
                        corners[(k + 2) % 6]] for k in (0, 2, 4)])
    polygon = _counter_clockwise(corners)
    # the coarse models' rule: three of the ring's points, 120° apart (their second moments
    # are the hexagon's too, but not their third: exact to degree 2), and the hexagon's
    # light spread as one parallelogram of its second moments, the image of a square of side
    # √(5/6) pitches on the regular lattice (a mean x² of 5/72, the hexagon's)
    # (a contiguous copy, not a strided view: the kernels' warm-up loads them for contiguous
    # arrays, and a view was a signature of its own that a fresh install compiled inside the
    # first hexagonal region, 5.5 s: docs/distance.md, "A kernel signature the warm-up missed
    # (stop 52)")
    three = np.ascontiguousarray(points[::2])
    square = math.sqrt(5.0 / 6.0) * a
    coarse = CellRule(False, corners[:3], three, np.full(3, 1.0 / 3.0),
                      three @ np.linalg.inv(three.T @ three) @ square, np.zeros((0, 3, 2)),
                      polygon)
    return CellRule(False, corners[:3], points, np.full(6, 1.0 / 6.0),
                    points @ np.linalg.inv(points.T @ points), pieces, polygon, coarse)


def _counter_clockwise(poly: np.ndarray) -> np.ndarray:
    """A polygon's corners (V, 2), in order about it, turned counter-clockwise."""
    x, y = poly[:, 0], poly[:, 1]
    area2 = float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
    return np.ascontiguousarray(poly if area2 > 0 else poly[::-1])


def _two_cells(lattice: LocalLattice, x: np.ndarray, y: np.ndarray):
    """Nearest and second-nearest lattice nodes of MLA points, and each point's distance to
    their bisector (the cell border it is nearest to): (n1x, n1y, n2x, n2y, gap)."""
    b = lattice.basis
    o = lattice.origin
    inv = lattice.inverse
    ex, ey = x - o[0], y - o[1]
    u = (inv[0, 0] * ex + inv[0, 1] * ey, inv[1, 0] * ex + inv[1, 1] * ey)
    la, lb, rect = _cell_shape(lattice)
    if rect:
        # rectangular cells: the nearest node by rounding, the nearest border along u or v
        i, j = np.rint(u[0]), np.rint(u[1])
        fu, fv = u[0] - i, u[1] - j
        gu = (0.5 - np.abs(fu)) * la
        gv = (0.5 - np.abs(fv)) * lb
        across_u = gu <= gv
        i2 = np.where(across_u, i + np.sign(fu), i)
        j2 = np.where(across_u, j, j + np.sign(fv))
        gap = np.minimum(gu, gv)
    else:
        fu, fv = np.floor(u[0]), np.floor(u[1])
        ru, rv = u[0] - fu, u[1] - fv
        d2 = []
        for di, dj in ((0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)):
            gx = b[0, 0] * (ru - di) + b[0, 1] * (rv - dj)
            gy = b[1, 0] * (ru - di) + b[1, 1] * (rv - dj)
            d2.append(gx * gx + gy * gy)
        d2 = np.array(d2)
        corner = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
        k1 = np.argmin(d2, axis=0)
        cols = np.arange(x.size)
        da = d2[k1, cols]
        d2[k1, cols] = np.inf
        k2 = np.argmin(d2, axis=0)
        db = d2[k2, cols]
        i, j = fu + corner[k1, 0], fv + corner[k1, 1]
        i2, j2 = fu + corner[k2, 0], fv + corner[k2, 1]
        di, dj = i2 - i, j2 - j
        sep = np.hypot(b[0, 0] * di + b[0, 1] * dj, b[1, 0] * di + b[1, 1] * dj)
        gap = (db - da) / (2.0 * sep)
    return (o[0] + b[0, 0] * i + b[0, 1] * j, o[1] + b[1, 0] * i + b[1, 1] * j,
            o[0] + b[0, 0] * i2 + b[0, 1] * j2, o[1] + b[1, 0] * i2 + b[1, 1] * j2, gap)


# Long vectors are reduced with einsum rather than BLAS: a threaded BLAS wakes its threads for
# a dot product of ~10⁴ residuals, and their spinning cost more CPU than the fit itself
# (2.4× a region's CPU time on a loaded 2-core machine).
def region_moments(geom: Geometry, image: np.ndarray, region: Region,
                   others: Sequence[Region] = ()) -> LensletMoments:
    """:func:`data_moments` of a region's box as :func:`measure_lenslet` fits them: the
    lenslets its blur shares with a touching one (``region.shared``) and, with
    :data:`OTHERS_EXCLUDED`, ``others``' lenslets left out."""
    exclude = np.concatenate([region.shared]
                             + ([o.lenslets for o in others] if OTHERS_EXCLUDED else []))
    return data_moments(geom, image, _region_box(geom, region, image.shape), exclude=exclude)


def _region_box(geom: Geometry, region: Region, shape) -> tuple[int, int, int, int]:
    x0, y0, x1, y1 = region.box_px
    pad = int(math.ceil(0.5 * geom.pitch_px))
    h, w = shape
    return max(0, x0 - pad), max(0, y0 - pad), min(w, x1 + pad), min(h, y1 + pad)


@dataclass(frozen=True)
class LensletFit:
    """Result of the lenslet-statistics fit of one region."""

    source_mm: np.ndarray  # (3,) point, or the midpoint of a line
    misfit: float
    sigma_distance_mm: float
    evaluations: int
    ok: bool
    reason: str = ""
    ends_mm: tuple = ()  # lines: (start (3,), end (3,))
    polished: bool = False  # the POLISH_RAYS model was needed (the fine one had not settled)
    polish_floor: float = math.nan  # the least misfit a polish of this fit can reach (bound)
    model_misfit: float = math.nan  # the fine and polishing models' disagreement at the fine
    #                                 fit (point fits): the share of a misfit that is the
    #                                 models' own ray samples, not the data
    coarse: bool = False  # a point fit's coarse stage on the cells, before the fine model's
    #                       steps (point_fit_stages' ``early`` yield)
    pixel_chi2: float = math.nan  # pixel_polish: the lit pixels' χ²/dof under the capture's
    #                               own noise model (its gain an upper bound; NaN: no gain)


LOG_DISTANCE_RANGE = (0.0, 16.0)  # a fit's log-distance parameter: 1 mm … 8.9 km


def _clip(v: float, lo: float, hi: float) -> float:
    """``np.clip`` of one number (NaN stays NaN), without numpy's per-call cost: the fits
    clip their parameters thousands of times a region."""
    v = float(v)
    return lo if v < lo else hi if v > hi else v


def _log_distance(q: np.ndarray) -> float:
    """The log-distance parameter ``q[0]`` clipped to :data:`LOG_DISTANCE_RANGE` (a wild
    optimiser step on a flat misfit must not overflow ``exp``)."""
    return _clip(q[0], *LOG_DISTANCE_RANGE)


def _at_far_bound(q: np.ndarray) -> bool:
    """True when the fit ran into the far end of the distance range (no finite answer)."""
    return bool(q[0] >= LOG_DISTANCE_RANGE[1] - 1e-6)


class SourceFrame:
    """A point source's fit parameters ``q = (log distance, x/L, y/L)``, L the distance to
    the stop: changing the distance keeps the line of sight through the stop centre, which
    decouples the three."""

    def __init__(self, profile: CameraProfile):
        lens = profile.main_lens
        self.z_front = lens.front_vertex_z_mm
        self.z_rim = lens.rim_z_mm

    def source(self, q: np.ndarray) -> np.ndarray:
        # a wild optimiser step stays a finite source (1 mm … 10⁷ mm, within ±45°)
        z = self.z_front - math.exp(_log_distance(q))
        along = self.z_rim - z
        return np.array([_clip(q[1], -1.0, 1.0) * along, _clip(q[2], -1.0, 1.0) * along, z])

    def params(self, s: np.ndarray) -> np.ndarray:
        along = self.z_rim - s[2]
        return np.array([math.log(self.z_front - s[2]), s[0] / along, s[1] / along])

    def fitted_params(self, fitted_mm) -> np.ndarray:
        """A fitted source's parameters (:attr:`Measurement.fitted_mm`): a point's ``(log
        distance, x/L, y/L)``, a line's ``(log distance, a/L, b/L)`` of its two ends (one
        distance, the first end's, as the line fit's)."""
        qs = [self.params(e) for e in np.asarray(fitted_mm, dtype=np.float64).reshape(-1, 3)]
        return qs[0] if len(qs) == 1 else np.r_[qs[0], qs[1][1:]]

    def fitted_source(self, q: np.ndarray) -> np.ndarray:
        """The source of :meth:`fitted_params`' parameters: a point (3,) or a line's two
        ends (2, 3)."""
        if len(q) == 3:
            return self.source(q)
        return np.array([self.source(q[:3]), self.source(np.r_[q[0], q[3:]])])


def summary(profile: CameraProfile, geom: Geometry, mom: LensletMoments,
            m: np.ndarray) -> np.ndarray:
    """Smooth low-dimensional summary of lenslet moments ``m`` (data or model), (4,).

    ``(b, x̄, ȳ, ρ)``: ``b`` is the isotropic gain of the slope field, spot offset ≈ a + b·(C − C̄)
    (≈ f_x/δ for an image point δ before the MLA: its sign tells the side of focus), (x̄, ȳ)
    the energy centroid of the lit lenslets (over 5 % of the brightest one's energy) and ρ
    their energy-weighted RMS radius about it (mm on the MLA; the blur's size). Compiled
    (:func:`lfcam.measure.kernels.moments_summary`).
    """
    from lfcam.measure.kernels import moments_summary

    return moments_summary(np.ascontiguousarray(m, dtype=np.float64), geom.lens_centres_mm,
                           mom.ids, geom.pitch_px * profile.sensor.pixel_pitch_mm)


def _starts(profile, geom, mom, frame, model):
    """Starting parameters from a geometric distance scan (lateral position from the chief ray
    through the light's centroid): where the model's slope-field gain crosses the data's
    (interpolated in log distance), and the scan point of least misfit."""
    lens = profile.main_lens
    f = lens.focal_length_mm
    t_data = summary(profile, geom, mom, mom.data)
    target = t_data[1:3]
    qs = []
    distances = np.geomspace(1.1 * f, 3e4, SCAN_DISTANCES)
    gains = chief_ray_gains(profile, geom.d_in_mm, distances)  # one trace for the scan
    for d, g in zip(distances, gains, strict=True):
        xy = chief_ray_offset(profile, geom.d_in_mm, d, target, gain=float(g))
        qs.append(frame.params(np.array([xy[0], xy[1], frame.z_front - d])))
    ms = model.simulate_each(np.array([frame.source(q) for q in qs]))
    scan = []
    for q, m in zip(qs, ms, strict=True):
        r = model.residual_of(m)
        scan.append((sq(r), q, summary(profile, geom, mom, m)))
    out = []
    bd, rd = t_data[0], t_data[3]
    for (f0, q0, t0), (f1, q1, t1) in zip(scan[:-1], scan[1:], strict=True):
        if not (np.isfinite(t0).all() and np.isfinite(t1).all()):
            continue
        if np.sign(t0[0]) != np.sign(bd) and np.sign(t1[0]) != np.sign(bd):
            continue  # the model's light is on the other side of focus
        for k, target in ((0, bd), (3, rd)):  # crossings of the slope gain and of the size
            if (t0[k] - target) * (t1[k] - target) <= 0 and t1[k] != t0[k]:
                t = (target - t0[k]) / (t1[k] - t0[k])
                out.append((min(f0, f1), q0 + t * (q1 - q0)))
    out.sort(key=lambda v: v[0])
    best = min(scan, key=lambda v: v[0])
    out.append((best[0], best[1]))  # and the scan point of least misfit
    out.sort(key=lambda v: v[0])
    starts = []
    for _, q in out:  # the best distinct candidates (5 % apart in distance)
        if all(abs(q[0] - p[0]) > 0.05 for p in starts):
            starts.append(q)
    return starts[:SCAN_KEEP], t_data


def _match_summary(profile, geom, mom, frame, model, q, t_data, iterations=SUMMARY_ITERATIONS,
                   jac0=None):
    """Broyden steps moving the model's summary at ``q`` onto the data's.

    The summary is smooth on the scale of a few % of distance, so the first Jacobian is taken
    by differences over 3 % (and ~1 % of a lenslet pitch sideways, scaled by distance), or is
    ``jac0`` (another model's match's, ending there); later steps update it by Broyden's rule
    (one model evaluation a step).

    Returns the parameters, the Jacobian (``None`` where the summary at ``q`` is not finite)
    and the normalised misfit of the summary there.
    """
    steps = np.array([0.03, 2e-3, 2e-3])
    pitch = profile.mla.pitch_mm
    scale = np.array([abs(t_data[0]) + 1e-3, pitch, pitch, 0.1 * t_data[3] + pitch])

    def t_of(qq):
        return summary(profile, geom, mom, model.simulate(frame.source(qq)))

    m = model.simulate(frame.source(q))  # (the moments at q: _recentre's residual there)
    t = summary(profile, geom, mom, m)
    if not np.isfinite(t).all():
        return q, None, math.inf
    err = float(np.linalg.norm((t - t_data) / scale))

    def t_many(qs):
        ms = model.simulate_sets([frame.source(qq) for qq in qs])
        return [summary(profile, geom, mom, m) for m in ms]

    def summary_jacobian(q, t):
        return fd_jacobian(t_of, t_many, q, t, steps)

    jac, fresh = (summary_jacobian(q, t), True) if jac0 is None else (jac0, False)
    for _ in range(iterations):
        if not np.isfinite(jac).all():
            break
        try:
            dq = np.linalg.lstsq(jac / scale[:, None], (t_data - t) / scale, rcond=None)[0]
        except np.linalg.LinAlgError:
            break
        dq[0] = float(np.clip(dq[0], -0.15, 0.15))
        m2 = model.simulate(frame.source(q + dq))
        t2 = summary(profile, geom, mom, m2)
        err2 = float(np.linalg.norm((t2 - t_data) / scale)) if np.isfinite(t2).all() else np.inf
        if not err2 < err:
            if fresh:
                break
            jac, fresh = summary_jacobian(q, t), True  # the Broyden update went stale: refresh
            continue
        jac = jac + np.outer((t2 - t) - jac @ dq, dq) / float(dq @ dq)
        fresh = False
        q, t, m, err = q + dq, t2, m2, err2
        if abs(dq[0]) < 2e-3:
            break
    if jac0 is None and err > SUMMARY_RECENTRE_ABOVE:
        q, err = _recentre(profile, geom, mom, frame, model, q, m, t, t_data, scale, err)
    return q, jac, err


def _recentre(profile, geom, mom, frame, model, q, m, t, t_data, scale, err):
    """Lateral steps after a summary match that failed (:data:`SUMMARY_RECENTRE_ABOVE`): the
    model's light centroid (the summary's ``x̄, ȳ`` on the MLA) moved onto the data's at
    ``q``'s distance, by the chief ray's gain there. Near focus the blur's core is a few
    lenslets wide inside a halo of a thousand, and a start two lenslets aside leaves a misfit
    of 0.8 that no local step mends; the centroid, which the halo holds, is smooth in the
    lateral position. At most :data:`SUMMARY_RECENTRE_STEPS` steps; the one of least
    residual misfit is kept where its misfit² is under :data:`SUMMARY_RECENTRE_GAIN` × the
    start's (else ``q`` itself: a line's blur moves a little and goes where it went). ``m``,
    ``t``: the model's moments and summary at ``q`` (the match's last evaluation).

    Returns the parameters and the summary's normalised misfit there (``err`` at ``q``)."""
    best = (SUMMARY_RECENTRE_GAIN * sq(model.residual_of(m)), q, err)
    for _ in range(SUMMARY_RECENTRE_STEPS):
        q_next = _centroid_step(profile, geom, frame, q, t, t_data)
        if q_next is None:
            break
        q = q_next
        m = model.simulate(frame.source(q))
        t = summary(profile, geom, mom, m)
        f = sq(model.residual_of(m))
        if f < best[0]:
            best = (f, q, float(np.linalg.norm((t - t_data) / scale))
                    if np.isfinite(t).all() else math.inf)
    return best[1], best[2]


def _centroid_step(profile: CameraProfile, geom: Geometry, frame: SourceFrame, q: np.ndarray,
                   t: np.ndarray, t_data: np.ndarray) -> np.ndarray | None:
    """``q`` moved sideways so that the model's light centroid (summary ``t`` at ``q``) lands
    on the data's (``t_data``): the centroids' offset on the MLA taken back to the object by
    the chief ray's gain at ``q``'s distance. None where that gain is 0 or ``t`` not finite."""
    d = math.exp(_log_distance(q))
    gain = float(chief_ray_gains(profile, geom.d_in_mm, d)[0])
    if gain == 0 or not np.isfinite(t).all():
        return None
    along = frame.z_rim - frame.source(q)[2]
    # (the chief ray's lateral offset at the object for the centroids' MLA offset)
    shift = chief_ray_offset(profile, geom.d_in_mm, d, t_data[1:3] - t[1:3], gain=gain)
    return q + np.r_[0.0, shift / along]


def _recentre_coarse(profile: CameraProfile, geom: Geometry, mom: LensletMoments,
                     frame: SourceFrame, model: LensletModel, q: np.ndarray, r: np.ndarray,
                     f: float) -> tuple[np.ndarray, np.ndarray, float]:
    """The coarse stage's end ``q`` (``model``'s residual ``r``, misfit² ``f``) moved by one
    :func:`_centroid_step`, where that lowers the misfit² (else as it was).

    On a large blur the coarse stage's lateral difference steps (:data:`COARSE_STEPS`, about
    a pitch on the MLA) span the range over which the rim lenslets' moments are linear in
    the source's place, and its Levenberg–Marquardt can end a fifth of a pitch aside at 8 ×
    its minimum's misfit, a place that the fine steps, which take its Jacobian, do not leave.
    The light centroid of a thousand lenslets places the blur to a few hundredths of a pitch
    (docs/distance.md, "A large blur's coarse end moved onto its light (stop 74)").
    Returns ``(q, r, f)``."""
    t_data = summary(profile, geom, mom, mom.data)
    t = summary(profile, geom, mom, model.simulate(frame.source(q)))
    if not (np.hypot(*(t_data[1:3] - t[1:3])) >= COARSE_RECENTRE_MIN_PITCH * profile.mla.pitch_mm):
        return q, r, f  # (on its light already, or no centroid: no step to try)
    q2 = _centroid_step(profile, geom, frame, q, t, t_data)
    if q2 is None:
        return q, r, f
    r2 = model.residual(frame.source(q2))
    f2 = sq(r2)
    return (q2, r2, f2) if f2 < f else (q, r, f)


def _polish_rays(n_fine: int, model_misfit: float, noise_misfit: float) -> int:
    """Rays of the polish's Levenberg–Marquardt model: :data:`POLISH_RAYS`, or where the
    region's photon noise dwarfs the models' own ray noise, as few as keep that ray noise at
    :data:`POLISH_NOISE_SHARE` of the noise misfit, and at least the fine model's ``n_fine``.

    ``model_misfit`` is the fine and polishing models' disagreement at the fine fit (mostly
    the fine model's ray noise, ∝ 1/√rays), ``noise_misfit`` the region's own
    (:func:`lfcam.measure.noise.NoiseModel.moments_misfit_of`; NaN, 0 or ∞: not known, the
    full polish)."""
    if not (POLISH_NOISE_SHARE > 0.0 and 0.0 < noise_misfit < math.inf
            and math.isfinite(model_misfit)):
        return POLISH_RAYS
    need = n_fine * (model_misfit / (POLISH_NOISE_SHARE * noise_misfit)) ** 2
    return int(min(max(need, n_fine), POLISH_RAYS))


def _refit_start(fun_r, q: np.ndarray, f: float, guess: np.ndarray | None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Where a line's refit starts, and the refit model's residual ``fun_r`` there: at
    ``guess`` (a linear step's end, or None) where the refit model's misfit² there is not
    over ``f``, the fine model's where the fit stands (``q``); else at ``q``. A wild step
    costs one evaluation more (none of the 31 refits started at a guess on system 1's far
    lines of the focus grid, with and without noise: there the refit model's misfit² at the
    guess was 0.3-0.9 × the fine one's)."""
    if guess is not None:
        r = fun_r(guess)
        if sq(r) <= f:
            return guess, r
    return q, fun_r(q)


def _accepted(accept: Callable[[float, float], bool], q: np.ndarray, sigma_log: float,
              shift_log: float, floor_rel: float) -> bool:
    """Whether ``accept(distance_mm, sigma_mm)`` takes the fit at ``q`` with its σ: the
    statistical ``sigma_log``, a shift the fit was spared (``shift_log``: a line's refit, a
    point's polish) and the floor ``floor_rel``, in quadrature (log distance)."""
    d = math.exp(_log_distance(q))
    return bool(accept(d, d * math.sqrt(sigma_log ** 2 + shift_log ** 2 + floor_rel ** 2)))


def lit_lenslets(mom: LensletMoments) -> int:
    """The lenslets a region's blur lights: those with over 5 % of the brightest one's energy
    (what the ray budgets and :func:`point_steps` scale with)."""
    return int((mom.data[:, 0] > 0.05 * mom.data[:, 0].max()).sum())


def point_steps(profile: CameraProfile, geom: Geometry, n_lit: int) -> np.ndarray:
    """Difference steps of a point fit's parameters (log distance, x/L, y/L) for a blur that
    lights ``n_lit`` lenslets.

    A lateral step ``h`` moves the chief ray, and the blur with it, by about ``h · d_in`` on
    the MLA. Near focus the blur is a few lenslets wide and its micro-images are sharp spots
    whose place moves fast with the source's: there the fixed step of ``COARSE_STEPS`` (0.12
    pitch on system 2) lies far outside the range over which the moments are linear (on the
    seed's system 2 point at 2800 mm, 10 mm off axis: the misfit is 0.0009 at the truth and
    0.7 a step away), and the Gauss–Newton steps built on such a Jacobian stalled 0.55 % off.
    So the lateral step moves the blur by at most ``LATERAL_STEP_BLUR`` × its diameter,
    ``pitch · √(4 n_lit / π)`` (docs/distance.md, "Difference steps sized to the blur"). The
    fine stages use these steps; the coarse stage keeps ``COARSE_STEPS``, as a step sized to
    the blur mostly differences its 3 000-ray model's own ray noise.
    """
    blur_mm = profile.mla.pitch_mm * math.sqrt(4.0 * max(n_lit, 1) / math.pi)
    lateral = min(float(COARSE_STEPS[1]), LATERAL_STEP_BLUR * blur_mm / geom.d_in_mm)
    return np.array([COARSE_STEPS[0], lateral, lateral])


def _polish_floor(r_check: np.ndarray, bound_above: float, jac: np.ndarray | None) -> float:
    """The least misfit a polish of the fine fit can reach (``r_check``: the polishing model's
    residual there), bounded below by ``(1 − POLISH_MAX_GAIN)`` × its misfit.

    Over ``bound_above`` the bound is raised by the Gauss–Newton step on ``r_check`` with the
    fine model's own Jacobian at the fit (``jac``, which the caller takes there; read only
    over ``bound_above``, None below it): the polish removes at most ``POLISH_GAIN_SAFETY`` ×
    the misfit² that linear step predicts, or ``POLISH_GAIN_MIN`` of it (docs/distance.md,
    "The polish's reach"). Where that step removes over ``POLISH_UNSETTLED`` of the misfit²
    (1: never), the fit is far from its own minimum and the bound is 0: the point is polished
    before a line is tried (docs/distance.md, "An unsettled point is polished before a line
    (stop 60)").
    """
    f = sq(r_check)
    floor = (1.0 - POLISH_MAX_GAIN) * math.sqrt(f)
    if not math.sqrt(f) > bound_above:
        return floor
    step_gain = linear_step(jac, r_check)
    if step_gain is None:
        return floor
    gain = step_gain[1]
    if gain > POLISH_UNSETTLED * f:
        return 0.0  # the fine fit has not reached its minimum: its polish may remove it all
    return max(floor, math.sqrt(max(f - max(POLISH_GAIN_SAFETY * gain, POLISH_GAIN_MIN * f),
                                        0.0)))


def _settled(fun, fun_many, fun_b, q_start: np.ndarray, q: np.ndarray, r: np.ndarray,
             r_check: np.ndarray, jac: np.ndarray, steps: np.ndarray,
             r_start: np.ndarray | None = None) -> tuple[bool, np.ndarray]:
    """Has the fine fit ``q`` (residual ``r`` of ``fun``) settled?

    Gauss–Newton with a fixed coarse Jacobian ``jac`` stops where that Jacobian, not the
    model's own, sees no descent, and the fine model's ray sample moves the minimum. So, with
    the fine model's own Jacobian at ``q`` (differences ``steps``), the Gauss–Newton step on
    ``r_check`` (the residual of a model of more rays at ``q``) must be under half of
    :data:`SETTLED_LOG` in log distance and remove less than :data:`SETTLED_GAIN` of its
    misfit², the minimum must be sharp (statistical σ under :data:`SETTLED_SIGMA`: along the
    shallow valley of a dim or far source the 80 000-ray minimum was found 1.6 % from the
    fine one with both tests passed); and the same Gauss–Newton from ``q_start`` through the
    turned pupil sample ``fun_b`` must land within :data:`SETTLED_LOG` of ``q``. With
    ``r_start`` (the fine model's residual at ``q_start``) and :data:`SETTLED_TURNED_LINEAR`
    that landing is read from the two samples' linear steps from ``q_start`` with ``jac``: the
    step on ``fun_b(q_start) − r_start`` (no step of the turned sample evaluated).

    Returns (settled, the fine model's Jacobian at ``q``).
    """
    jac_q = fd_jacobian(fun, fun_many, q, r, steps)
    jtj = gram(jac_q)
    step_gain = linear_step(jac_q, r_check)
    if step_gain is None:
        return False, jac_q
    step, gain = step_gain
    if not (abs(step[0]) < 0.5 * SETTLED_LOG and gain < SETTLED_GAIN * sq(r_check)):
        return False, jac_q
    # a shallow minimum (dim or far sources): the step above is no guide along its valley
    f = sq(r_check)
    try:
        var = f / max(r_check.size - len(q), 1) * np.linalg.inv(jtj)[0, 0]
    except np.linalg.LinAlgError:
        return False, jac_q
    if not math.sqrt(max(var, 0.0)) < SETTLED_SIGMA:
        return False, jac_q
    if SETTLED_TURNED_LINEAR and r_start is not None:
        shift = linear_step(jac, fun_b(q_start) - r_start)
        return bool(shift is not None and abs(float(shift[0][0])) < SETTLED_LOG), jac_q
    q_b, _, _ = gauss_newton_fixed(fun_b, q_start, fun_b(q_start), jac, FINE_ITERATIONS,
                                   min_trial=FINE_MIN_TRIAL_LOG)
    return bool(abs(q_b[0] - q[0]) < SETTLED_LOG), jac_q


def _profile_sigma(fun, fun_many, q: np.ndarray, n_res: int, sigma_rel: float,
                   r0: np.ndarray | None = None, jac0: np.ndarray | None = None, *,
                   steps: np.ndarray) -> float:
    """σ of the log distance from the misfit profile (lateral position refitted at each trial
    distance), for blurs of a few lenslets (:data:`PROFILE_LENSLETS`).

    Statistical width: on each side the trial step starts at the Jacobian's σ and grows ×3
    until the profile misfit has risen by the fit's variance unit ``s² = f / (n − 3)`` (as
    for the Jacobian's covariance); the side's σ is the step scaled to Δf = s² (a quadratic
    profile). Ridge: a side where a step of ``PROFILE_RIDGE_LOG`` (10 %) raises the misfit by
    less than ``PROFILE_RIDGE_RISE`` times the model's systematic part of it (at most
    ``PROFILE_FLOOR``², the mismatch of the exact model on bright far sources) leaves the
    distance to that mismatch: such sources were measured 5–8 % off with a statistical σ of
    1.3–2.3 %. Returns the larger side's σ, or ``inf`` on a ridge or when a side does not
    rise by s² within a factor 2 in distance (the data do not fix the distance). ``r0`` and
    ``jac0``: ``fun(q)`` and its difference Jacobian (steps ``steps``), when known.

    The lateral refit at a trial distance starts where the Jacobian at ``q`` predicts the
    lateral minimum and takes up to ``PROFILE_GN_STEPS`` Gauss–Newton steps with that
    Jacobian's lateral columns (one evaluation a step; the lowest misfit seen is the
    profile's); the first trial is ``PROFILE_START`` Jacobian σ out, where a quadratic
    profile has risen past s². Levenberg–Marquardt with a fresh difference Jacobian at every
    trial, from one σ out, took 21–71 evaluations a profile on the seed grid, this 12–34
    (docs/distance.md, "Fewer evaluations: a cheaper σ profile and polish").
    """
    r0 = fun(q) if r0 is None else r0
    f0 = sq(r0)
    s2 = f0 / max(n_res - 3, 1)
    if not s2 > 0.0:
        return sigma_rel
    systematic = min(f0, PROFILE_FLOOR**2)
    jac = fd_jacobian(fun, fun_many, q, r0, steps) if jac0 is None else jac0
    jp, jz = jac[:, 1:], jac[:, 0]
    try:
        solve = np.linalg.inv(gram(jp))
    except np.linalg.LinAlgError:
        return math.inf
    lateral_slope = -(solve @ jt(jp, jz))  # the lateral minimum's drift per unit of t

    def rise(t: float) -> float:
        p = q[1:] + t * lateral_slope
        best = math.inf
        for _ in range(PROFILE_GN_STEPS):
            r = fun(np.r_[q[0] + t, p])
            f = sq(r)
            if not f < best:
                break
            best = f
            p = p - solve @ jt(jp, r)
        return best - f0

    worst = 0.0
    for sign in (1.0, -1.0):
        if rise(sign * PROFILE_RIDGE_LOG) < PROFILE_RIDGE_RISE * systematic:
            return math.inf
        t = min(max(PROFILE_START * sigma_rel, 1e-4), PROFILE_MAX_LOG)
        while True:
            d = rise(sign * t)
            if d >= s2:
                worst = max(worst, t * math.sqrt(s2 / d))
                break
            if t >= PROFILE_MAX_LOG:
                return math.inf
            t = min(3.0 * t, PROFILE_MAX_LOG)
    return worst


def fit_lenslet_point(profile: CameraProfile, geom: Geometry, image: np.ndarray,
                      region: Region, polish_above: float = math.inf,
                      mom: LensletMoments | None = None) -> LensletFit:
    """Fit a point source to the region's lenslet moments (:func:`point_fit_stages`, run to
    its end)."""
    *_, fit = point_fit_stages(profile, geom, image, region, polish_above, mom)
    return fit


def point_fit_stages(profile: CameraProfile, geom: Geometry, image: np.ndarray,
                     region: Region, polish_above: float = math.inf,
                     mom: LensletMoments | None = None,
                     bound_above: float = math.inf,
                     gates: Callable[[float], tuple[float, float]] | None = None,
                     early: bool = False,
                     accept: Callable[[float, float], bool] | None = None,
                     noise_misfit: float = math.nan,
                     start_q: np.ndarray | None = None) -> Iterator[LensletFit]:
    """Fit a point source to the region's lenslet moments (module docstring).

    Stages: distance scan and summary matching with the coarse model (``COARSE_RAYS``),
    Levenberg–Marquardt with the coarse model, then Gauss–Newton steps with the fine model
    (``RAYS_PER_LENSLET`` per lit lenslet) and the coarse Jacobian; the same steps through a
    turned pupil sample check that the fine fit has settled (:func:`_settled`), and only a
    fit that has not is polished with ``POLISH_RAYS``, or one whose misfit is over
    ``polish_above`` (a misfit a gate will read: the polish lowers it by up to ~15 %;
    ``0`` always polishes, as the lens calibration does). ``mom``: the region's
    :func:`data_moments`, when the caller has them.

    A start where the cells apply (:func:`cells_apply`) is matched on the scan's rays first,
    and on the coarse cells only where that brought the summary within
    :data:`SUMMARY_MATCHED` of the data's (:data:`SUMMARY_SCAN_FIRST`: a line's blur, which a
    point's summary cannot match, spends no cells evaluations there).
    A large blur whose best start has the cells apply about it (:func:`cells_apply`,
    :data:`POINT_CELLS`) takes its first look on them, as a line does: the coarse and fine
    models sample the lenslet cells (n = :data:`LINE_CELLS_COARSE`, then
    :meth:`LensletModel.fine_cells`) and the first yield's polishing model is the finer
    sub-grid :data:`LINE_CELLS_SETTLE`. Its answer comes from the ray models, their
    Gauss–Newton steps started from the cells' fit, then the settled test and the polish.

    Yields twice (three times with ``early``, below): the fine fit with the polishing model's
    misfit at it (``polished=False``, no σ: a caller reads only its misfits), then the final
    fit. A caller that learns from the first that the region is no point (a line fits it far
    better) stops there and saves the polish and the σ profile.

    ``gates``: when given, ``polish_above`` and ``bound_above`` are ``gates(m)``, with ``m``
    the fine and polishing models' disagreement at the fine fit (``‖r_fine − r_polish‖``, the
    first yield's ``model_misfit``): a gate that reads the data's misfit need not look below
    what the models' own ray samples leave (:func:`measure_lenslet`).

    ``early``: a fit on the cells yields once more before those two, at the coarse stage's
    minimum (``coarse=True``): its misfit and ``polish_floor`` as the first yield's, read
    there (the polishing model's residual, the floor's linear step with the Jacobian the fine
    steps would take). On a line's blur the fine steps do not move a point's misfit (0.96-1.04
    × the coarse stage's on the focus grid's lines), and a caller that finds a line there
    saves them (docs/distance.md, "A line tried at the point's coarse stage (stop 47)").

    ``accept`` (optional): ``accept(distance_mm, sigma_mm)``, whether an answer that certain
    is enough for the caller. A fit the settled test would polish (not one near a gate) is
    answered without the polish where the fine fit, with its σ, the linear step still to go to
    the polishing model's minimum and :data:`SIGMA_FLOOR_REL` added in quadrature, is
    accepted; that σ is the one it reports (docs/distance.md, "A polish only where the
    tolerance needs it (stop 51)").

    ``noise_misfit`` (optional): the region's noise misfit (:func:`measure_lenslet`'s), with
    which the polish runs on fewer rays where the photons' noise dwarfs the models' own
    (:func:`_polish_rays`); NaN: the full polish.

    ``start_q`` (optional): the one start ``(log distance, x/L, y/L)``, an earlier answer of
    the same region (a refit on its moments less a neighbour's light,
    :func:`measure_lenslet`'s ``start``): no distance scan and no summary matching; the
    stages from the coarse one on are the same.
    """
    if mom is None:
        mom = data_moments(geom, image, _region_box(geom, region, image.shape))
    nan3 = np.full(3, np.nan)
    if not mom.norm > 0 or len(mom.ids) < 3:
        yield LensletFit(nan3, np.nan, np.nan, 0, False, RegionStatus.EMPTY)
        return
    n_lit = lit_lenslets(mom)
    n_rays = int(np.clip(RAYS_PER_LENSLET * n_lit, MIN_RAYS, MAX_RAYS))
    steps = point_steps(profile, geom, n_lit)
    frame = SourceFrame(profile)

    def fun_of(model):
        return lambda q: model.residual(frame.source(q))

    def many_of(model):
        return lambda qs: [model.residual_of(m)
                           for m in model.simulate_sets([frame.source(q) for q in qs])]

    scan = LensletModel(profile, geom, mom, SCAN_RAYS)
    if start_q is not None:
        starts, t_data = [np.asarray(start_q, dtype=np.float64)], None
    else:
        starts, t_data = _starts(profile, geom, mom, frame, scan)
    # a large blur on the cells where they apply about its start: each start is matched on
    # them where they apply about it (a start on the caustic's side of focus, where they do
    # not, on the rays), and the best start's model goes on
    coarse_rays = int(np.clip(COARSE_PER_LENSLET * n_lit, COARSE_RAYS, MAX_RAYS // 2))
    coarse_of = [LensletModel(profile, geom, mom, coarse_rays)]  # rays, cells
    cells_ok = [False] * len(starts)
    if POINT_CELLS and n_lit >= LINE_CELLS_MIN_LIT:
        cells_ok = [cells_apply(profile, geom, mom, n_lit,
                                np.array([frame.source(q0 + [dl, 0.0, 0.0])
                                          for dl in LINE_CELLS_PROBE_LOG])) for q0 in starts]
        if any(cells_ok):
            coarse_of.append(LensletModel(profile, geom, mom, coarse_rays,
                                          cells=LINE_CELLS_COARSE))
    # (a large blur's summary matched on the rays: on fewer of them than its coarse model's)
    summary_model = (LensletModel(profile, geom, mom, SUMMARY_LARGE_RAYS)
                     if 0 < SUMMARY_LARGE_RAYS < coarse_rays and n_lit >= LINE_BIN_MIN_LIT
                     else None)
    best = None
    scan_ends: list[np.ndarray] = []  # where the starts matched on the cells had their scan match
    for k, q0 in enumerate(starts):
        if (k > 0 and best[1] <= START_GOOD
                and sq(scan.residual(frame.source(q0))) >= START_HOPELESS):
            continue  # its light misses the data's: no summary matching has brought one back
        model = coarse_of[int(cells_ok[k])]
        if start_q is not None:
            q = q0  # (an earlier answer: its summary matches the data's already)
        elif cells_ok[k] and SUMMARY_SCAN_FIRST:
            # a line's blur, which a point's summary cannot match, stays where the scan's rays
            # leave it (its Broyden steps on the cells: 8-14 evaluations for nothing); a
            # point's goes on on the cells (with the scan's end alone, its coarse stage took
            # an iteration more)
            q, jac_s, err = _match_summary(profile, geom, mom, frame, scan, q0, t_data)
            if any(abs(q[0] - e[0]) < SUMMARY_SAME_LOG
                   and float(np.max(np.abs(q[1:] - e[1:]))) < SUMMARY_SAME_ANGLE
                   for e in scan_ends):
                continue  # an earlier start's basin, matched on the cells already
            scan_ends.append(q)
            if err < SUMMARY_MATCHED and jac_s is not None:
                q = _match_summary(profile, geom, mom, frame, model, q, t_data, jac0=jac_s)[0]
        else:
            q = _match_summary(profile, geom, mom, frame, summary_model or model, q0,
                               t_data)[0]
        r = model.residual(frame.source(q))
        f = sq(r)
        if best is None or f < best[1]:
            best = (q, f, r, k)
    on_cells = cells_ok[best[3]]
    coarse = coarse_of[int(on_cells)]
    fine = LensletModel(profile, geom, mom, n_rays,
                        cells=0 if not on_cells else coarse.fine_cells())
    q, r, f, jac = levenberg_marquardt(fun_of(coarse), best[0], COARSE_STEPS,
                                       COARSE_ITERATIONS, 1e-3, many_of(coarse), r0=best[2],
                                       ftol=COARSE_CELLS_FTOL if on_cells else 0.0)
    if n_lit >= COARSE_RECENTRE_MIN_LIT and not on_cells:
        q, r, f = _recentre_coarse(profile, geom, mom, frame, coarse, q, r, f)
    fun = fun_of(fine)
    q_c = q
    r = r_c = fun(q_c)  # (r_c: the fine model's residual where its steps start)
    if on_cells and not coarse.cell_shape[2]:
        # a hexagonal lattice's borders cut n = 2's sub-cells, and its Jacobian is not fit
        # for the steps (as the line fit's): the fine model's own, for them and the rays'
        # below (a 3500 mm point's answer +0.17 % at 5σ on n = 2's: docs/distance.md, "Whole
        # hexagonal cells (stop 45)")
        jac = fd_jacobian(fun, many_of(fine), q_c, r, steps)
    # The ray sample's own noise moves the minimum: on 100-200 lenslet blurs off axis, by ~1 %
    # of the distance at 12 000-20 000 rays (a lateral shift trades against distance), 0.3 %
    # at 80 000. The same fit through a turned pupil sample measures that shift; only when it
    # (or the step still to go) is over SETTLED_LOG is the fit polished with a model of
    # POLISH_RAYS and its own Jacobian (docs/distance.md, "The misses fixed", "Speed").
    turned = LensletModel(profile, geom, mom, n_rays, phase=1.0)
    # (on the cells the polishing model is the settled test's finer sub-grid)
    polish = LensletModel(profile, geom, mom, POLISH_RAYS,
                          cells=LINE_CELLS_SETTLE if on_cells else 0)
    fun_p = fun_of(polish)
    counted = [scan, *coarse_of, fine, turned, polish]  # the models whose evaluations count
    if summary_model is not None:
        counted.append(summary_model)

    def evaluations() -> int:
        return sum(m.evaluations for m in counted)

    fine_jacobians: dict[bytes, np.ndarray] = {}  # the fine model's, by q (fine_jacobian)

    def fine_jacobian(q: np.ndarray, r: np.ndarray) -> np.ndarray:
        # the fine model's Jacobian at q (its residual r there) by differences, taken once: the
        # polish floor's (first_look) is the one a polish near a gate starts from
        key = q.tobytes()
        if key not in fine_jacobians:
            fine_jacobians[key] = fd_jacobian(fun, many_of(fine), q, r, steps)
        return fine_jacobians[key]

    def first_look(q: np.ndarray, r: np.ndarray, jac_q: np.ndarray | None,
                   coarse_stage: bool) -> tuple[LensletFit, np.ndarray]:
        # the fit at q (the fine model's residual r there) as the polishing model reads it,
        # with the floor its polish could reach (jac_q: the fine steps' Jacobian at q, else by
        # differences), the gates set from the two models' disagreement; and the polishing
        # model's residual
        nonlocal polish_above, bound_above
        r_p = fun_p(q)
        model_misfit = math.sqrt(sq(r - r_p))
        if gates is not None:
            polish_above, bound_above = gates(model_misfit)
        far = _at_far_bound(q)  # the fit fails here, with the final fit's reason
        if jac_q is None and math.sqrt(sq(r_p)) > bound_above:
            jac_q = fine_jacobian(q, r)  # (the floor reads it only over bound_above)
        return LensletFit(frame.source(q), math.sqrt(sq(r_p)), math.nan, evaluations(),
                          not far, RegionStatus.NO_SOLUTION if far else "",
                          polish_floor=_polish_floor(r_p, bound_above, jac_q),
                          model_misfit=model_misfit, coarse=coarse_stage), r_p

    if early and on_cells:
        yield first_look(q_c, r, jac, True)[0]
    q, r, f = gauss_newton_fixed(fun, q_c, r, jac, FINE_ITERATIONS,
                                 min_trial=FINE_MIN_TRIAL_LOG)
    r_fine = r  # the fine model's residual at q (the σ profile's start, when q stays)
    look, r_p = first_look(q, r, None, False)
    yield look
    if on_cells:
        # A point's answer comes from the rays: on the cells the quintic pupil map's area
        # element leaves points 0.04-0.07 % short (docs/distance.md, "Large point blurs on
        # the cells (stop 44)"). The fine ray model's Gauss–Newton steps from the cells' fit,
        # with the cells' Jacobian (the coarse one's; the fine one's on a hexagonal
        # lattice); then the settled test and the polish as below.
        fine = LensletModel(profile, geom, mom, n_rays)
        fine_jacobians.clear()  # (the cells' fine model's, not this one's)
        polish = LensletModel(profile, geom, mom, POLISH_RAYS)
        counted += [fine, polish]
        fun, fun_p = fun_of(fine), fun_of(polish)
        q_c = q
        r_c = fun(q_c)
        q, r, f = gauss_newton_fixed(fun, q_c, r_c, jac, FINE_ITERATIONS,
                                     min_trial=FINE_MIN_TRIAL_LOG)
        r_fine = r
        r_p = fun_p(q)
        if gates is not None:  # (the polish's gate as the ray models' disagreement sets it)
            polish_above, bound_above = gates(math.sqrt(sq(r - r_p)))
    # a misfit near a gate is polished whatever the settled test says: do not run it then
    near_gate = not math.sqrt(sq(r_p)) <= polish_above
    if near_gate:
        # polished whatever. Near a gate that measure_lenslet set (not where the caller asks
        # for every polish: polish_above 0, the lens calibration), its Levenberg–Marquardt
        # starts from the fine model's Jacobian at q, as a polish the settled test asks for
        # does (first_look's, when it took it), not from the polishing model's own (3 ×
        # POLISH_RAYS; docs/distance.md, "A polish near a gate from the fine model's
        # Jacobian (stop 76)")
        from_fine = POLISH_NEAR_GATE_FINE_JAC and gates is not None
        settled, jac_q = False, fine_jacobian(q, r) if from_fine else None
    else:
        settled, jac_q = _settled(fun, many_of(fine), fun_of(turned), q_c, q, r, r_p, jac,
                                  steps, r_c)
    polished = not settled
    to_go = 0.0  # the linear step still to go to the polishing model's minimum (log distance),
    #              kept in σ where the caller accepts the fine fit with it
    if (polished and not near_gate and accept is not None and jac_q is not None
            and POLISH_BY_TOLERANCE):
        linear = linear_step(jac_q, r_p)
        if linear is not None:
            s_log, step_log = log_distance_sigma(jac_q, r_p), abs(float(linear[0][0]))
            if (math.isfinite(s_log) and math.isfinite(step_log)
                    and _accepted(accept, q, s_log, step_log, SIGMA_FLOOR_REL)):
                polished, to_go = False, step_log
    if not polished:  # the misfit as the polishing model sees it (the fine one adds its
        #               own noise)
        jac, r, f = jac_q, r_p, sq(r_p)
    else:
        # (a polish the settled test asked for whose first step, that test's own, does not
        # lower the polishing model's misfit ends there: POLISH_FIRST_OR_STOP)
        # (where the photons' noise dwarfs the rays', on fewer rays: POLISH_NOISE_SHARE)
        lm_model, r_lm = polish, r_p
        n_polish = _polish_rays(n_rays, math.sqrt(sq(r - r_p)), noise_misfit)
        if n_polish <= n_rays:
            lm_model, r_lm = fine, r  # (the fine model itself, its residual at q)
        elif n_polish < POLISH_RAYS:
            lm_model = LensletModel(profile, geom, mom, n_polish)
            counted.append(lm_model)
            r_lm = fun_of(lm_model)(q)
        # a secant's "settled" over the noise read again with the fine model's Jacobian
        # (POLISH_CONFIRM_NOISE; no noise misfit known: never)
        confirm_above = (POLISH_CONFIRM_NOISE * noise_misfit
                         if POLISH_CONFIRM_NOISE > 0 and noise_misfit > 0 else math.inf)
        q, r, f, jac_fine = levenberg_marquardt(fun_of(lm_model), q, steps, FINE_LM_ITERATIONS,
                                                1e-3, many_of(lm_model), r0=r_lm,
                                                jac0=jac_q, broyden=True,
                                                settle_log=POLISH_SETTLE_LOG,
                                                min_trial=0.0 if near_gate
                                                else POLISH_MIN_TRIAL_LOG,
                                                trial_gain=SETTLED_GAIN,
                                                first_or_stop=(POLISH_FIRST_OR_STOP
                                                               and not near_gate),
                                                confirm_above=confirm_above,
                                                confirm_below=POLISH_CONFIRM_BELOW,
                                                confirm_jac=lambda qq: fd_jacobian(
                                                     fun, many_of(fine), qq, fun(qq), steps))
        if jac_fine is not None:
            jac = jac_fine
    misfit = math.sqrt(f)
    source = frame.source(q)
    dist = math.exp(_log_distance(q))
    sigma_d = dist * math.hypot(log_distance_sigma(jac, r), to_go)
    ridge = False
    if n_lit <= PROFILE_LENSLETS and math.isfinite(sigma_d) and not _at_far_bound(q):
        s_rel = _profile_sigma(fun_of(fine), many_of(fine), q, len(r), sigma_d / dist,
                               *((None, None) if polished else (r_fine, jac_q)), steps=steps)
        ridge = not math.isfinite(s_rel)  # the data do not fix the distance
        if not ridge:
            sigma_d = max(sigma_d, dist * s_rel)
    evals = evaluations()
    if ridge:
        yield LensletFit(source, misfit, np.inf, evals, False, RegionStatus.NEAR_FOCUS)
    elif (_at_far_bound(q)
          or not source[2] < frame.z_front - 1.02 * profile.main_lens.focal_length_mm):
        yield LensletFit(source, misfit, sigma_d, evals, False, RegionStatus.NO_SOLUTION)
    else:
        yield LensletFit(source, misfit, sigma_d, evals, True, polished=polished)


def _line_points(frame: SourceFrame, q: np.ndarray, count: int = LINE_POINTS) -> np.ndarray:
    """``count`` equally bright points along the segment of ``q = (log d, a/L, b/L)``."""
    z = frame.z_front - math.exp(_log_distance(q))
    along = frame.z_rim - z
    xy = segment_points(q[1:3] * along, q[3:5] * along, count)
    return np.column_stack([xy, np.full(count, z)])


def line_model(model: LensletModel, frame: SourceFrame, count: int, steps: np.ndarray,
               ends_on_rays: bool = False):
    """The line model of ``count`` points (:func:`_line_points`): its residual function
    ``fun(q, bins=None)`` and its Jacobian ``jac(q, r, bins=None)`` (``r = fun(q, bins)``),
    steps ``steps``; with ``bins`` (:class:`CellBins`) both on its super-cells, from the same
    moments (the last few kept: a residual read both ways costs one evaluation). The last
    Jacobian is kept too: asked again at the same ``q`` and ``bins`` it costs nothing.

    The Jacobian is built from the points' own moments: every point shifted at once along x
    (then y) by the lateral step, each point's change weighted by its share of either
    endpoint (1 − t, t), gives both endpoints' lateral columns from one trace, and the
    distance column is a difference. Three traces of the line instead of the five of
    forward differences, the points' moments at ``q`` kept from the residual
    (docs/distance.md, "A line's Jacobian from its points"). On the cells
    (:data:`LINE_JACOBIAN_ENDS`) the points are shifted across the line only, and the
    columns along it come from the line's two end points: two traces of the line and two
    points; on the rays too with ``ends_on_rays`` (a refit's model: :data:`LINE_REFIT_ENDS`).
    """
    t = (np.arange(count) + 0.5) / count  # each point's place along the line
    kept: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def moments(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # the points' moments summed (K, 4), and summed with each one's weighted by its place
        # t along the line (its share of the far end; 1 − t of the near end's)
        key = q.tobytes()
        if key not in kept:
            if len(kept) >= 4:
                kept.pop(next(iter(kept)))
            s, st = model.simulate_weighted(_line_points(frame, q, count), one, 1, t, 1)
            kept[key] = (s[0], st[0])
        return kept[key]

    one = np.zeros(count, dtype=np.int64)  # every point in one group
    # the points shifted along x, then y, and the line at the distance step (each set of
    # points at the same place in the stack as the base's: the same pupil turns)
    shifted = np.repeat(np.arange(3, dtype=np.int64), count)
    # across and ends: the points shifted across the line, the distance step, the two ends
    ends_groups = np.r_[shifted[:2 * count], 2, 3]

    def lateral(s: np.ndarray, st: np.ndarray, m0: np.ndarray, t0: np.ndarray) -> tuple:
        # the points' changes from the base's, each weighted by its share of the near end
        # (1 − t) and of the far one (t): Σ (1 − tᵢ)·Δmᵢ = ΔS − ΔT, Σ tᵢ·Δmᵢ = ΔT
        return (s - m0) - (st - t0), st - t0

    def traced_ends(q: np.ndarray, pts: np.ndarray, shift: float, qd: np.ndarray,
                    m0: np.ndarray, t0: np.ndarray) -> tuple | None:
        # The lateral changes from the points shifted across the line and the line's two end
        # points: along the line the points' weighted sums of derivatives telescope,
        # Σ (1 − tᵢ)·∂mᵢ/∂s ≈ (M/N − m(a))/h and Σ tᵢ·∂mᵢ/∂s ≈ (m(b) − M/N)/h (h the points'
        # spacing, M their sum, m(a), m(b) a point at either end), so the line's 3 traces of
        # its N points become 2 and two points (docs/distance.md, "A line's Jacobian along
        # it from its ends (stop 56)"); None for a line of no length
        along = frame.z_rim - pts[0, 2]
        a, b = q[1:3] * along, q[3:5] * along
        length = float(np.hypot(*(b - a)))
        if not length > 0.0:
            return None
        e = (b - a) / length
        nv = np.array([-e[1], e[0]])
        m, mt = model.simulate_weighted(
            np.concatenate([pts + [shift * nv[0], shift * nv[1], 0.0],
                            _line_points(frame, qd, count),
                            [[a[0], a[1], pts[0, 2]], [b[0], b[1], pts[0, 2]]]]),
            ends_groups, 4, np.r_[t, np.zeros(count + 2)], 3)
        mean = m0 / count
        h = length / count
        slide = (shift / h * (mean - m[2]), shift / h * (m[3] - mean))
        moved = []
        for across, ds in zip(lateral(m[0], mt[0], m0, t0), slide, strict=True):
            moved.append([m0 + e[k] * ds + nv[k] * across for k in (0, 1)])
        return m[1], moved

    def traced_points(pts: np.ndarray, shift: float, qd: np.ndarray, m0: np.ndarray,
                      t0: np.ndarray) -> tuple:
        # every point shifted along x, then y; each one's change weighted by its share of
        # either end (the weighted sums added in the deposit: docs/distance.md, "A line's
        # weighted sums in the deposit (stop 75)")
        m, mt = model.simulate_weighted(np.concatenate([pts + [shift, 0.0, 0.0],
                                                        pts + [0.0, shift, 0.0],
                                                        _line_points(frame, qd, count)]),
                                        shifted, 3, np.tile(t, 3), 3)
        moves = [lateral(m[k], mt[k], m0, t0) for k in (0, 1)]
        return m[2], [[m0 + moves[k][end] for k in (0, 1)] for end in (0, 1)]

    last_jac: list = []  # (q's bytes, bins, the Jacobian) of the last call

    def jac(q: np.ndarray, r: np.ndarray, bins: CellBins | None = None) -> np.ndarray:
        key = q.tobytes()
        if last_jac and last_jac[0] == key and last_jac[1] is bins:
            return last_jac[2]
        pts = _line_points(frame, q, count)
        shift = steps[1] * (frame.z_rim - pts[0, 2])
        qd = q.copy()
        qd[0] += steps[0]
        m0, t0 = moments(q)
        r0 = model.residual_of(m0, bins)  # = r
        # the moments at the distance step, and with either end moved along x and y (from
        # the ends on the cells, where a cells model that folded samples rays from then on,
        # and on the rays with ends_on_rays)
        got = (traced_ends(q, pts, shift, qd, m0, t0)
               if LINE_JACOBIAN_ENDS and ((model.cells and not model.folded) or ends_on_rays)
               else None)
        far, moved = got if got is not None else traced_points(pts, shift, qd, m0, t0)
        out = np.column_stack([(model.residual_of(far, bins) - r0) / steps[0],
                               *[(model.residual_of(mk, bins) - r0) / steps[1]
                                 for end in moved for mk in end]])
        last_jac[:] = [key, bins, out]
        return out

    def fun(q: np.ndarray, bins: CellBins | None = None) -> np.ndarray:
        return model.residual_of(moments(q)[0], bins)

    return fun, jac


def _frame_cut(region: Region, shape: tuple[int, ...], pitch_px: float) -> bool:
    """Whether ``region``'s box reaches within a lenslet pitch of the frame's edge (the
    lenslets the edge cuts are not in the map)."""
    x0, y0, x1, y1 = region.box_px
    return min(x0, y0, shape[1] - x1, shape[0] - y1) < pitch_px


def cells_apply(profile: CameraProfile, geom: Geometry, mom: LensletMoments, n_lit: int,
                points: np.ndarray) -> bool:
    """Whether a blur of ``n_lit`` lit lenslets is modelled on the lenslet cells
    (``LensletModel(cells=n)``): at least :data:`LINE_CELLS_MIN_LIT` lenslets, a lattice, and
    every one of ``points`` (the starts' probes) with its whole pupil passing and a map to the
    MLA that is one to one."""
    return (n_lit >= LINE_CELLS_MIN_LIT
            and lattice_of(geom, profile.mla.pitch_mm) is not None
            and LensletModel(profile, geom, mom, LINE_MIN_RAYS, cells=LINE_CELLS_COARSE)
            .invertible(points))


def _footprint(geom: Geometry, mom: LensletMoments, energy: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Energy-weighted centre (2,) and covariance (2, 2) of the lenslet centres (MLA mm) of a
    region's lenslets that hold over 5 % of the brightest one's ``energy``."""
    lit = energy > 0.05 * energy.max()
    c = geom.lens_centres_mm[mom.ids[lit]]
    w = energy[lit]
    cbar = (c * w[:, None]).sum(0) / w.sum()
    dc = c - cbar
    return cbar, (dc.T * w) @ dc / w.sum()


def fit_lenslet_line(profile: CameraProfile, geom: Geometry, image: np.ndarray,
                     region: Region, point: LensletFit | None = None,
                     useful_below: float = math.inf, mom: LensletMoments | None = None,
                     accept: Callable[[float, float], bool] | None = None,
                     start_q: np.ndarray | None = None) -> LensletFit:
    """Fit a line source (equally bright points half a pitch apart, 5 parameters) to the
    region's lenslet moments. Starts: the point fit's distance and centre, and the best node of
    a distance scan (centre from the chief ray through the light's centroid); both with the
    footprint's long axis and the image length from its second moments (along − across =
    Lᵢ²/12).

    ``useful_below``: the misfit a line must reach to change the caller's answer. A fit whose
    coarse misfit is over ``LINE_STOP_COARSE`` × that (that at least ``LINE_STOP_FLOOR``), or
    whose fine Gauss–Newton misfit is over ``LINE_STOP_FINE`` × that, stops there
    (``ok=False``, status ``poor-fit``): the later stages lower the misfit by at most 2.7× and
    2.7× on the measured regions (docs/distance.md, "A compiled inner loop, lines that stop
    when they cannot win", "Fewer evaluations: a cheaper σ profile and polish"). ``mom``: the
    region's :func:`data_moments`, when the caller has them.

    ``accept`` (optional): ``accept(distance_mm, sigma_mm)``, whether an answer that certain
    is enough for the caller (its ``--tolerance``). A line whose settled test asks for the
    refit with more rays is not refitted when its σ, with the measured sampling shift and the
    line σ floor added in quadrature, is accepted; that σ is then the one it reports
    (docs/distance.md, "A line's refit only where the tolerance needs it"). A line on
    super-cells (below) ends after its fine Gauss–Newton steps where the answer there (the
    linear step to the fine and turned samples' mean minimum), with half the two samples'
    shift in its σ, is accepted (:data:`LINE_FINE_BY_TOLERANCE`).

    A ray-sampled blur lighting :data:`LINE_BIN_MIN_LIT` lenslets or more runs its race, its
    coarse stage and the fine model's Gauss–Newton steps on 2 × 2 super-cells
    (:class:`CellBins`, :data:`LINE_BIN`), the coarse model on :data:`LINE_BIN_RAYS` × fewer
    rays.

    ``start_q`` (optional): the one start ``(log distance, a/L, b/L)`` (:func:`_line_points`),
    an earlier line answer of the same region (a refit on its moments less a neighbour's
    light, :func:`measure_lenslet`'s ``start``): no point fit, no distance scan, no race
    (docs/distance.md, "A refit from the first answer (stop 72)").
    """
    if mom is None:
        mom = data_moments(geom, image, _region_box(geom, region, image.shape))
    nan3 = np.full(3, np.nan)
    warm = start_q is not None
    if point is None and not warm:
        point = fit_lenslet_point(profile, geom, image, region, mom=mom)
    if not warm and not point.ok:
        return LensletFit(nan3, np.nan, np.nan, point.evaluations, False, point.reason)
    frame = SourceFrame(profile)
    cbar, cov = _footprint(geom, mom, mom.data[:, 0])
    # the line adds L²/12 along its axis to a point's footprint (MLA plane)
    evals, evecs = np.linalg.eigh(cov)
    length_mla = math.sqrt(max(12.0 * (evals[1] - evals[0]), 0.0))
    # A point's own footprint is round only near the axis: off axis, vignetting and coma
    # stretch it radially (elongation (λ₁ − λ₂)/(λ₁ + λ₂) of the point fit's model: 0.2 at
    # 60 %, 0.3 at 80 % of system 1's half-field; 0.04-0.06 on system 2 there). A line
    # across that stretch (60 % off axis, at 135° to the radius) was started along the
    # radius and ended in a wrong basin as a spot, 24 % off; at 80 %, 6 of 12 lines behind
    # focus. Where the point's footprint is stretched by over LINE_STRETCHED, the starts
    # are turned (docs/distance.md, "Lines across the field's stretch"). The footprint less
    # the point's own is the turns' first axis: alone, on axis, it put seed lines up to
    # 3.4 % off (a small blur's footprint is square or hexagonal on the lattice).
    n_lit = lit_lenslets(mom)
    stretched = False
    # (a footprint of a few lenslets is square or hexagonal, not round: 0.06-0.1 on axis)
    if n_lit >= LINE_STRETCH_MIN_LIT and not warm:
        _, cov_point = _footprint(geom, mom, LensletModel(profile, geom, mom, COARSE_RAYS)
                                  .simulate(point.source_mm)[:, 0])
        ev_point, axes_point = np.linalg.eigh(cov_point)
        # ... and only where the data's axis is the stretch's (else it is the line's own)
        stretched = bool((ev_point[1] - ev_point[0])
                         > LINE_STRETCHED * (ev_point[1] + ev_point[0])
                         and abs(float(evecs[:, 1] @ axes_point[:, 1]))
                         > math.cos(math.radians(LINE_STRETCH_AXIS_DEG)))
        evals_c, evecs_c = np.linalg.eigh(cov - cov_point)
        length_c = math.sqrt(max(12.0 * (evals_c[1] - evals_c[0]), 0.0))

    def mla_to_object(d: float, g: float) -> tuple[float, float]:
        # at a trial distance d (g: the chief ray's gain there): object mm per MLA mm, and the
        # distance to the stop that turns object mm into the lateral parameters (x/L)
        gain = chief_ray_offset(profile, geom.d_in_mm, d, np.array([1.0, 0.0]), gain=g)[0]
        return abs(gain), frame.z_rim - (frame.z_front - d)

    def segment(d: float, centre_mm: np.ndarray | None = None, g: float | None = None,
                axis: np.ndarray = evecs[:, 1], length: float = length_mla) -> np.ndarray:
        # the footprint's long axis and length (or ``axis``, ``length`` on the MLA), seen from
        # a trial distance d (g: the chief ray's gain there, when known)
        if g is None:
            g = float(chief_ray_gains(profile, geom.d_in_mm, d)[0])
        gain, along = mla_to_object(d, g)
        centre = (chief_ray_offset(profile, geom.d_in_mm, d, cbar, gain=g) if centre_mm is None
                  else centre_mm) / along
        half = 0.5 * length * gain / along * axis
        return np.r_[math.log(d), centre - half, centre + half]

    def oriented(q: np.ndarray, lengths: tuple[float, ...] = ()) -> list[np.ndarray]:
        # A short line inside a wide blur (behind focus) barely elongates the footprint: its
        # axis is then noise (measured 30-90° off on lines 3 pitches long) and its length
        # short, and the local fit from there stalls. So the starts are the best
        # LINE_TURNED_STARTS, by the scan model, of the segment turned through
        # LINE_START_ANGLES and lengthened by LINE_START_EXTRA_PITCH (docs/distance.md,
        # "Short lines behind focus").
        centre, half = 0.5 * (q[1:3] + q[3:5]), 0.5 * (q[3:5] - q[1:3])
        norm = float(np.hypot(*half))
        axis = half / norm if norm > 0 else evecs[:, 1]
        d = math.exp(_log_distance(q))
        gain, along = mla_to_object(d, float(chief_ray_gains(profile, geom.d_in_mm, d)[0]))
        extra = 0.5 * LINE_START_EXTRA_PITCH * profile.mla.pitch_mm * gain / along
        # ``lengths`` (MLA mm): more lengths to try, each also lengthened
        halves = [norm] + [0.5 * v * gain / along for v in lengths]
        cands = []
        for k in range(LINE_START_ANGLES):
            a = math.pi * k / LINE_START_ANGLES
            u = np.array([math.cos(a) * axis[0] - math.sin(a) * axis[1],
                          math.sin(a) * axis[0] + math.cos(a) * axis[1]])
            for h in halves:
                for hh in (h, h + extra):
                    cands.append(np.r_[q[0], centre - hh * u, centre + hh * u])
        costs = [sq(r) for r in many_of(scan_model, n_scan)(cands)]
        return [cands[i] for i in np.argsort(costs)[:LINE_TURNED_STARTS]]

    if warm:
        q0 = np.asarray(start_q, dtype=np.float64)
    else:
        d0 = float(frame.z_front - point.source_mm[2])
        q0 = segment(d0, point.source_mm[:2])
    # points along the segment at most LINE_SPACING_PITCH apart on the MLA: 12 points 2
    # pitches apart left lines behind focus up to 1.7 % long (their sum of blurs is combed
    # at the spacing); the rays a point shrink in proportion (the total stays) down to
    # LINE_MIN_SHARE: at a quarter, each point's own ray noise put lines 1-7 % off
    # (docs/distance.md, "Lines: points half a pitch apart")
    n_pts = int(np.clip(math.ceil(length_mla / (LINE_SPACING_PITCH * profile.mla.pitch_mm)),
                        LINE_POINTS, LINE_POINTS_MAX))
    share = max(LINE_POINTS / n_pts, LINE_MIN_SHARE)
    # Every point of a line lights most of the blur: each needs about as many rays per lit
    # lenslet as a point source does, or the model's own sampling noise (misfit 0.10 at the
    # truth with 250 rays a point on an 800-lenslet blur, 0.017 with 4000) hides the minimum.
    # The fine model has at least half the point polish's rays in all (the full polish's with
    # one shared pupil sample; the points' turned samples do as well with half: docs/distance.md,
    # "A line's points, each with its own turn of the pupil sample"): on small noise-free blurs
    # a far line leaves 0.002-0.004 as a point, and 12 000 rays left the line fit no lower.
    # a large blur's models sample the pupil on points fixed on the lenslet cells: their
    # Jacobians by differences are not the ray sample's noise (docs/distance.md, "Samples
    # fixed on the lenslet cells")
    on_cells = False  # (decided once the starts are known, below)

    def model(rays_12: float, share: float = share, count: int = n_pts,
              cells: int = 0, phase: float = 0.0) -> LensletModel:
        # the 12 points' rays a point, shared; each of the ``count`` points its own turn
        return LensletModel(profile, geom, mom, max(int(share * rays_12), LINE_MIN_RAYS),
                            phase=phase, turn_every=count if LINE_TURNS else 0,
                            cells=cells if on_cells else 0)

    # the coarse stage finds the basin: at most LINE_COARSE_POINTS points (a long line's 48
    # points with half the rays each cost twice the 12 points' rays); the scan, which picks
    # its start, at most LINE_SCAN_POINTS
    n_coarse = min(n_pts, LINE_COARSE_POINTS)
    share_c = max(LINE_POINTS / n_coarse, LINE_MIN_SHARE)
    # (its rays a point as the coarse stage's; on a small blur half as many points)
    n_scan = min(n_coarse, LINE_SCAN_POINTS if n_lit >= LINE_SCAN_SMALL_LIT
                 else LINE_SCAN_POINTS_SMALL)
    scan_model = model(max(COARSE_RAYS // LINE_COARSE_SHARE, 200), share_c, n_scan)
    steps = np.r_[COARSE_STEPS[0], np.full(4, COARSE_STEPS[1])]


    def many_of(model, count):
        return lambda qs: [model.residual_of(m) for m in model.simulate_sets(
            [_line_points(frame, q, count) for q in qs])]

    def scanned_starts() -> list[np.ndarray]:
        # Starts: the point fit's distance, and the best node of a distance scan of the line
        # model. Behind focus a line's point fit lands 30-50 % off (docs/distance.md), too far
        # for the local fit to come back from.
        distances = np.geomspace(1.1 * profile.main_lens.focal_length_mm, 3e4, SCAN_DISTANCES)
        gains_scan = chief_ray_gains(profile, geom.d_in_mm, distances)
        scan = [segment(float(d), g=float(g)) for d, g in zip(distances, gains_scan, strict=True)]
        if (LINE_SCAN_RECENTRE and region is not None
                and _frame_cut(region, image.shape, geom.pitch_px)):
            # the frame cuts the model's light on the region's lenslets as it cuts the data's: the
            # segment at each node moves by the chief-ray offset between the two centroids
            for _ in range(LINE_SCAN_RECENTRE):
                models = scan_model.simulate_sets([_line_points(frame, q, n_scan) for q in scan])
                moved = []
                for q, m, d, g in zip(scan, models, distances, gains_scan, strict=True):
                    if not m[:, 0].max() > 0:
                        moved.append(q)
                        continue
                    c_model, _ = _footprint(geom, mom, m[:, 0])
                    dxy = (chief_ray_offset(profile, geom.d_in_mm, float(d), cbar, gain=float(g))
                           - chief_ray_offset(profile, geom.d_in_mm, float(d), c_model,
                                              gain=float(g)))
                    _, along = mla_to_object(float(d), float(g))
                    moved.append(np.r_[q[0], q[1:3] + dxy / along, q[3:5] + dxy / along])
                scan = moved
        costs = [sq(r) for r in many_of(scan_model, n_scan)(scan)]
        best_scan = scan[int(np.argmin(costs))]
        # the scan's best node is a start of its own unless it lies in the point's basin (stopping
        # when the first start is already below the scan's best node put behind-focus lines 1.7 %
        # off on average: the scan's coarser model reads higher misfits, not a worse basin)
        starts = [q0] if abs(best_scan[0] - q0[0]) < 0.05 else [q0, best_scan]
        if LINE_FAR_POINT_START and _at_far_bound(q0):
            # a point fit run out to the far bound tells nothing of where the line is: the scan's
            # best node is the one start (the far bound and its turned copies raced too, and lost:
            # on the hexagonal 380 mm line at 80 % of the field three of them, ~17 ms)
            starts = [best_scan]
        elif stretched:
            # the footprint's axis is the field's: turned starts about the axis of the footprint
            # less the point's, at that length and the footprint's own
            starts += oriented(segment(d0, point.source_mm[:2], axis=evecs_c[:, 1],
                                       length=length_c), (length_mla,))
        # a footprint elongated by more than LINE_TURN_BELOW has an axis to trust (3 mm lines in
        # a 5-7 mm blur: 9-17 %): the turned start is for the round ones (short lines: 0.2-0.5 %)
        elif (evals[1] - evals[0]) < LINE_TURN_BELOW * (evals[1] + evals[0]):
            # the footprint's own axis stays a start: on small blurs the scan model's few rays
            # misjudge the turn (a seed line)
            starts += [t for t in oriented(q0) if not np.array_equal(t, q0)]
        return starts

    # (a refit from an earlier answer: that answer alone)
    starts = [q0] if warm else scanned_starts()
    # On the cells where they apply at every start, 11 % nearer and 25 % farther: in front of
    # focus, near the caustic, a fit that starts where the map is one to one may go where it
    # folds (and its models then turn to rays midway: 560 mm lines in front of a 1 m focus
    # took 0.16-0.30 s instead of 0.11-0.15 with the start alone checked). Behind a 1 m focus
    # the map folds nearer than ~1280 mm.
    on_cells = cells_apply(profile, geom, mom, n_lit,
                           np.concatenate([_line_points(frame, st + [dl, 0, 0, 0, 0], 3)
                                           for st in starts for dl in LINE_CELLS_PROBE_LOG]))
    coarse_rays = np.clip(LINE_COARSE_PER_LENSLET * n_lit, COARSE_RAYS // LINE_COARSE_SHARE,
                          LINE_COARSE_MAX_RAYS)
    n_fine = n_pts
    if on_cells:
        # the fine stage on half the points, the coarse stage (and the race) on a third: the
        # settled test's model has them all (LINE_CELLS_POINTS_SHARE, LINE_CELLS_COARSE_SHARE)
        n_fine = max(LINE_POINTS, math.ceil(LINE_CELLS_POINTS_SHARE * n_pts))
        n_coarse = max(LINE_CELLS_COARSE_POINTS, math.ceil(LINE_CELLS_COARSE_SHARE * n_pts))
    # a large ray-sampled blur's coarse stage on super-cells, with as many rays a super-cell
    # as a lenslet had (LINE_BIN)
    lattice = None if on_cells or LINE_BIN < 2 or n_lit < LINE_BIN_MIN_LIT else lattice_of(
        geom, profile.mla.pitch_mm)
    bins = None if lattice is None else CellBins.of(geom, mom, lattice, LINE_BIN)
    if bins is not None:
        coarse_rays = max(int(coarse_rays / LINE_BIN_RAYS), COARSE_RAYS // LINE_COARSE_SHARE)
    coarse = model(coarse_rays, share_c, n_coarse, LINE_CELLS_COARSE)
    # (its Gauss–Newton steps and the gate after them on the fine model too)
    fine = model(LINE_FINE_RAYS, count=n_fine, cells=coarse.fine_cells())
    fun_every, jac_c = line_model(coarse, frame, n_coarse, steps)
    fun_c = fun_every
    if bins is not None:
        fun_c, jac_c = partial(fun_every, bins=bins), partial(jac_c, bins=bins)
    # the starts race: LINE_RACE_ITERATIONS coarse iterations each, then the leader alone runs
    # the rest (docs/distance.md, "A line's Jacobian from its points")
    settling: list[LensletModel] = []  # more models whose evaluations count (the race's on
    #                                     the cells, the settled test's)
    race_c, race_j = fun_c, jac_c
    if coarse.cells:
        # on the cells the race, which only picks the basin, runs on the rays (an evaluation on
        # the cells costs ~2.5× one of the race's rays), a lone start too; the leader then goes
        # on on the cells
        race = model(coarse_rays, share_c, n_coarse)
        race_c, race_j = line_model(race, frame, n_coarse, steps)
        settling.append(race)
    race_iterations = (LINE_CELLS_RACE_ITERATIONS if coarse.cells
                       else LINE_RACE_ITERATIONS if len(starts) > 1 else COARSE_ITERATIONS)
    if warm:
        race_iterations = min(race_iterations, LINE_WARM_ITERATIONS)
    # the starts race from the best placed: one whose misfit² where it starts is over
    # LINE_RACE_START_RATIO × the best start's, or LINE_RACE_HOPELESS × the best race's end,
    # does not run (a far start, or an axis turned the wrong way)
    r_starts = [race_c(start) for start in starts]  # (the race's first evaluations)
    f_starts = [sq(r0) for r0 in r_starts]
    best_start = min(f_starts)
    heats = []
    for k in np.argsort(f_starts, kind="stable"):
        best_end = min((h[2] for h in heats), default=math.inf)  # the earlier heats' best
        if heats and (f_starts[k] > LINE_RACE_START_RATIO * best_start
                      or f_starts[k] > LINE_RACE_HOPELESS * best_end):
            continue
        if race_iterations == 0:  # (a warm start: its Jacobian alone)
            heats.append((starts[k], r_starts[k], f_starts[k], race_j(starts[k], r_starts[k])))
            continue
        heats.append(levenberg_marquardt(race_c, starts[k], steps, race_iterations, 1e-3,
                                         r0=r_starts[k], jac_of=race_j,
                                         stop_above=LINE_RACE_GIVE_UP * best_end))
    q, r, f, jac = min(heats, key=lambda heat: heat[2])
    if coarse.cells:
        # Gauss–Newton on the coarse cells, its Jacobian refreshed only where the steps are
        # still long after LINE_CELLS_GN_STEPS: Levenberg–Marquardt's fresh Jacobian at every
        # iteration cost three evaluations each, to reach a minimum the fine model moves by
        # 0.4-0.7 % anyway (docs/distance.md, "Fewer evaluations on the cells")
        r = fun_c(q)
        f = sq(r)
        jac = jac_c(q, r)  # (the race's, from the rays: one more round, no less CPU)
        for _ in range(LINE_CELLS_JACOBIANS):
            f_round = f
            q, r, f = gauss_newton_fixed(fun_c, q, r, jac, LINE_CELLS_GN_STEPS,
                                         skip_below=LINE_CELLS_COARSE_STEP_LOG)
            step = linear_step(jac, r)
            if (step is None or abs(float(step[0][0])) < LINE_CELLS_COARSE_STEP_LOG
                    or f > (1.0 - LINE_CELLS_COARSE_GAIN) * f_round
                    or step[1] < LINE_CELLS_COARSE_GAIN * f):
                break
            jac = jac_c(q, r)
    elif len(starts) > 1:
        q, r, f, jac_lead = levenberg_marquardt(fun_c, q, steps,
                                                COARSE_ITERATIONS - LINE_RACE_ITERATIONS, 1e-3,
                                                r0=r if race_c is fun_c else None,
                                                jac_of=jac_c)
        jac = jac if jac_lead is None else jac_lead

    sigma_log = None  # the fit's statistical σ (log distance), once computed
    sampling_log = 0.0  # the fine sample's shift, kept in σ where its refit was not needed

    def evaluations() -> int:
        return ((0 if point is None else point.evaluations) + scan_model.evaluations
                + coarse.evaluations
                + fine.evaluations
                + sum(m.evaluations for m in settling))

    def stopped(stage_misfit: float) -> LensletFit:
        return LensletFit(nan3, stage_misfit, np.nan, evaluations(), False,
                          RegionStatus.POOR_FIT)

    def line_fit_at(q: np.ndarray, f: float, sigma_log: float,
                    spared_log: float) -> LensletFit:
        # the answer at q (cost f), its σ: the statistical ``sigma_log`` and a shift the fit
        # was spared, in quadrature (log distance)
        z = _line_points(frame, q, 2)[0, 2]
        along = frame.z_rim - z
        ends = (np.r_[q[1:3] * along, z], np.r_[q[3:5] * along, z])
        sigma_d = math.exp(_log_distance(q)) * math.hypot(sigma_log, spared_log)
        mid = 0.5 * (ends[0] + ends[1])
        if _at_far_bound(q):
            return LensletFit(mid, math.sqrt(f), sigma_d, evaluations(), False,
                              RegionStatus.NO_SOLUTION, ends_mm=ends)
        return LensletFit(mid, math.sqrt(f), sigma_d, evaluations(), True, ends_mm=ends)

    # the coarse model's own ray noise lowers its misfit too: it stops only well above it
    # (on super-cells, the misfit over every lenslet: the same moments)
    f_stop = f if bins is None else sq(fun_every(q))
    if math.sqrt(f_stop) > LINE_STOP_COARSE * max(useful_below, LINE_STOP_FLOOR):
        return stopped(math.sqrt(f_stop))
    fun, jac_f = line_model(fine, frame, n_fine, steps,
                            ends_on_rays=LINE_FINE_ENDS and bins is None)  # (LINE_FINE_ENDS)
    r = fun(q)
    if fine.cells:
        # the fine model's own Jacobian (on the cells the fine model makes the steps too) for
        # its steps, the settled test and σ: n = 2's is not fit for them on a hexagonal
        # lattice, whose borders cut its sub-cells (its distance column 10 % off n = 6's,
        # 0.4 % on the rectangular; the answers 0.26 % from n = 6's minimum on a 3400 mm line)
        jac = jac_f(q, r)
    if bins is None and not fine.cells and not LINE_RAYS_FINE_GN:
        # on the rays the Levenberg–Marquardt below, on the fine model's own Jacobian, starts
        # where the coarse stage ended: the coarse Jacobian's four steps crept toward a
        # minimum the fine Jacobian's steps then went on to (LINE_RAYS_FINE_GN)
        f = sq(r)
    elif bins is None:
        q, r, f = gauss_newton_fixed(
            fun, q, r, jac, FINE_ITERATIONS,
            skip_below=LINE_CELLS_FINE_STEP_LOG if fine.cells else 0.0,
            trusted=LINE_REFIT_TRUST_LOG if fine.cells and LINE_CELLS_TRUSTED else 0.0)
    else:
        # the coarse Jacobian is the super-cells': the fine model's steps read them too (a
        # Jacobian over every lenslet taken again on the coarse rays: refits in 3 of scene
        # (b)'s 10 lines, errors up by half)
        q = gauss_newton_fixed(partial(fun, bins=bins), q, fun(q, bins), jac,
                               FINE_ITERATIONS)[0]
        r = fun(q)
        f = sq(r)
    if math.sqrt(f) > LINE_STOP_FINE * useful_below:
        return stopped(math.sqrt(f))
    probe: list = []  # the settled test's residual function (its turned model's), once made

    def fun_turned():
        if not probe:
            turned = model(fine.rx.size, 1.0, cells=LINE_CELLS_SETTLE, phase=1.0)
            settling.append(turned)
            probe.append(line_model(turned, frame, n_pts, steps)[0])
        return probe[0]

    if (bins is not None and accept is not None and LINE_FINE_BY_TOLERANCE
            and math.sqrt(f) < useful_below):
        # With a tolerance, the fit may end where the fine model's Gauss–Newton steps on the
        # super-cells ended. The answer there: the linear step (the fine model's Jacobian) to
        # the minimum of the fine and turned samples' mean, a model of twice the rays; its σ:
        # the statistical one with half the two samples' shift in quadrature (the error of a
        # two-sample mean is half their difference's, as a lone sample's is the whole
        # difference's: the settled test's rule); its misfit (and the residual of its σ) the
        # fine model's where the steps ended. Ends there where the caller accepts it (with
        # the line σ floor); else the Jacobian (line_model keeps it) is the
        # Levenberg–Marquardt's first (docs/distance.md, "A line on super-cells that ends
        # where the tolerance accepts it (stop 77)").
        jac_gn = jac_f(q, r)
        r_t = fun_turned()(q)
        mean_step = linear_step(jac_gn, 0.5 * (r + r_t))
        shift = linear_step(jac_gn, r_t - r)
        if (mean_step is not None and shift is not None
                and abs(float(mean_step[0][0])) <= LINE_EXIT_STEP_LOG):
            q_mean = q - mean_step[0]
            s_log = log_distance_sigma(jac_gn, r)
            spared = 0.5 * abs(float(shift[0][0]))
            if (math.isfinite(spared) and math.isfinite(s_log)
                    and _accepted(accept, q_mean, s_log, spared, LINE_SIGMA_FLOOR_REL)):
                return line_fit_at(q_mean, f, s_log, spared)

    early: list = []  # the settled test's shift, the log distance it was read at and the
    #                   refit's start, when read before the fine fit's last iteration

    def settled_early(it: int, q_it: np.ndarray, r_it: np.ndarray, jac_it: np.ndarray) -> bool:
        # Before the fine fit's last iteration: the turned sample's step less the fine one's
        # at the same point and with the same Jacobian is the shift between their minima
        # whether or not the fit has reached its own. A line it would refit goes to the
        # refit from here, whose own Jacobian and Gauss–Newton steps finish the fit
        # (LINE_REFIT_EARLY); any other takes its last iteration, and keeps that verdict
        # unless the iteration moved it by more than LINE_SETTLED_LOG (then the fit had not
        # settled, and the test is read again where it ends, as without this rule).
        if it != LINE_FINE_LM_ITERATIONS - 2 or not math.sqrt(sq(r_it)) < useful_below:
            return False
        r_t = fun_turned()(q_it)
        shift = linear_step(jac_it, r_t - r_it)
        moved = math.inf if shift is None else abs(float(shift[0][0]))
        early[:] = [moved, float(q_it[0]), None]
        if not moved > LINE_SETTLED_LOG:
            return False
        if accept is not None and math.isfinite(moved) and _accepted(
                accept, q_it, log_distance_sigma(jac_it, r_it), moved, LINE_SIGMA_FLOOR_REL):
            return False
        # The refit starts at the linear step to the two samples' mean minimum, the better
        # guess of the refit model's: its one Jacobian, taken there, is then taken nearer its
        # minimum. That Jacobian's Gauss–Newton fixed point lies 0.2-0.4 % short of the
        # refit model's minimum on a 3400 mm line at 80 % of system 1's field (noise-free),
        # by where it is taken: started where the fit stands, the line landed 0.14 % off the
        # old path's; started here, 0.05 % (docs/distance.md, "The settled test before the
        # fine fit's last iteration (stop 58)").
        mean_step = linear_step(jac_it, 0.5 * (r_it + r_t))
        if mean_step is not None:
            early[2] = q_it - mean_step[0]
        return True

    if not fine.cells:
        q, r, f, jac_fine = levenberg_marquardt(
            fun, q, steps, LINE_FINE_LM_ITERATIONS, 1e-3, r0=r, jac_of=jac_f,
            settle_log=LINE_SETTLE_LOG, pause=settled_early if LINE_REFIT_EARLY else None,
            min_trial=LINE_REFIT_MIN_TRIAL_LOG if LINE_FINE_TRIAL_LATERAL > 0.0 else 0.0,
            trial_gain=1.0, trial_lateral=LINE_FINE_TRIAL_LATERAL,
            fail_stop=LINE_FINE_FAIL_STOP_LOG)
        if jac_fine is not None:
            jac = jac_fine
    if math.sqrt(f) < useful_below:
        # The fine model's own ray sample moves a line's minimum, most where the data fix the
        # distance least (far behind focus the blur grows by ~0.4 % for 1 % of distance): on
        # system 1's small vignetted blurs at 80 % of the half-field, 3400 mm, by +1.9 %
        # (noise-free), at 4.4σ. One Gauss–Newton step with the fit's Jacobian on the
        # residual of a turned pupil sample measures that shift (as the point fit's settled
        # test does); a line that moves by more than LINE_SETTLED_LOG is refitted with
        # LINE_REFINE × the rays (docs/distance.md, "A line's settled test").
        # On the cells the second sample is a finer sub-grid (LINE_CELLS_SETTLE) of all the
        # line's points, whose quadrature is the better one: the answer goes to its minimum
        # (the cells' own bias against a 400 000-ray model, on system 2's lines behind
        # focus: +0.02 to +0.10 % at n = 4, within ±0.01 % at n = 6: docs/distance.md,
        # "Samples fixed on the lenslet cells"), by that step or, where it is longer than
        # LINE_CELLS_SETTLED_LOG, by Gauss–Newton on that model (docs/distance.md, "Cheaper
        # stages (stop 40)").
        if early and (early[0] > LINE_SETTLED_LOG
                      or abs(float(q[0]) - early[1]) <= LINE_SETTLED_LOG):
            moved, shift = early[0], None  # (on the rays, read before the last iteration)
        else:
            fun_t = fun_turned()
            r_t = fun_t(q)
            shift = linear_step(jac, r_t)
            moved = math.inf if shift is None else abs(float(shift[0][0]))
        refit = moved > LINE_SETTLED_LOG
        if fine.cells and shift is not None:
            # the step to n = 6's minimum: as it is, or, where long, by Gauss–Newton on n = 6
            if moved > LINE_CELLS_SETTLED_LOG:
                q, r, f = gauss_newton_fixed(fun_t, q, r_t, jac, LINE_CELLS_SETTLE_STEPS,
                                             skip_below=LINE_REFIT_STEP_LOG)
            else:
                q = q - shift[0]
            refit = False
        if refit and accept is not None and math.isfinite(moved):
            # the refit is for the sample's share of the error: not needed where the caller
            # accepts the answer with that share in its σ
            sigma_log = log_distance_sigma(jac, r)
            if _accepted(accept, q, sigma_log, moved, LINE_SIGMA_FLOOR_REL):
                refit, sampling_log = False, moved
        if refit:
            refined = model(min(int(LINE_REFINE * fine.rx.size), LINE_REFINE_MAX_RAYS), 1.0,
                            cells=LINE_CELLS_REFIT)
            settling.append(refined)
            fun_r, jac_r = line_model(refined, frame, n_pts, steps,
                                      ends_on_rays=LINE_REFIT_ENDS)
            q, r = _refit_start(fun_r, q, f, early[2] if early else None)
            jac = jac_r(q, r)
            # (LINE_REFIT_MIN_TRIAL_LOG ≥ LINE_REFIT_STEP_LOG: no step under the latter either)
            q, r, f = gauss_newton_fixed(
                fun_r, q, r, jac, LINE_REFIT_STEPS, min_trial=LINE_REFIT_MIN_TRIAL_LOG,
                trusted=LINE_REFIT_TRUST_LOG if LINE_REFIT_TRUSTED else 0.0)
            sigma_log = None
    if sigma_log is None:
        sigma_log = log_distance_sigma(jac, r)
    return line_fit_at(q, f, sigma_log, sampling_log)


def _pixel_model(profile: CameraProfile, geom: Geometry, mom: LensletMoments, lit: np.ndarray,
                 n_rays: int) -> tuple[LensletModel, np.ndarray, np.ndarray]:
    """A :class:`LensletModel` whose "lenslets" are the box's pixels where ``lit`` (its first
    moment each pixel's light: the rays binned as the sensor bins them), and those pixels'
    rows and columns in the box."""
    rows, cols = np.nonzero(lit)
    labels = np.full(lit.shape, -1, dtype=np.int32)
    labels[rows, cols] = np.arange(rows.size, dtype=np.int32)
    x0, y0 = mom.box[:2]
    centres = np.column_stack([cols + x0, rows + y0]).astype(np.float64)
    pixels = LensletMoments(mom.box, labels, np.arange(rows.size), centres,
                            np.zeros((rows.size, 4)), 1.0)
    return LensletModel(profile, geom, pixels, n_rays), rows, cols


def _local_gain(e: np.ndarray, light: np.ndarray, read_sigma: float) -> float | None:
    """The photon gain (image units per photo-electron) the pixels' own residuals ``e``
    show about the model's ``light``: the median of ``(e² − σ_r²) / light`` over the pixels
    whose light is over :data:`PIXEL_GAIN_LIGHT` × σ_r, over the median of χ² with one
    degree of freedom (a neighbour's stray pixels do not move a median). None where fewer
    than :data:`PIXEL_GAIN_PIXELS` pixels are that bright, or the estimate is not positive:
    the capture's gain stands (an upper bound where measured, none where the capture cannot
    measure it and the profile does not state it)."""
    bright = light > PIXEL_GAIN_LIGHT * read_sigma
    if int(bright.sum()) < PIXEL_GAIN_PIXELS:
        return None
    g = float(np.median((e[bright] ** 2 - read_sigma**2) / light[bright])) / CHI2_1_MEDIAN
    return g if g > 0 and math.isfinite(g) else None


def _log_sigma(jac: np.ndarray, f: float, n: int) -> float:
    """The first parameter's σ from a weighted Jacobian ``jac`` and misfit² ``f`` of ``n``
    residuals (scaled up by χ²/dof where that is over 1); 0 where ``jac`` is singular."""
    try:
        with np.errstate(over="ignore", invalid="ignore"):  # (a wild column: not finite)
            var = float(np.linalg.inv(jac.T @ jac)[0, 0])
    except np.linalg.LinAlgError:
        return 0.0
    chi2 = f / max(n - jac.shape[1], 1)
    return math.sqrt(var * max(1.0, chi2)) if var > 0 and math.isfinite(var) else 0.0


def pixel_polish(profile: CameraProfile, geom: Geometry, image: np.ndarray, mom: LensletMoments,
                 source_mm: np.ndarray, noise: NoiseModel) -> LensletFit | None:
    """A point's lenslet answer refitted on the region's lit pixels.

    The pixels the model lights at ``source_mm`` (over :data:`PIXEL_WINDOW_SHARE` of its
    brightest, grown by :data:`PIXEL_WINDOW_GROW`; only the box's pixels that ``mom`` reads)
    are fitted pixel by pixel with a :data:`PIXEL_RAYS` ray model: Gauss–Newton on (log
    distance, x/L, y/L, log intensity), each pixel weighted by its noise (``noise``: read σ
    and photon gain, at the model's light where the steps start), the mean reading of a
    capture that clips its noise at zero modelled (:func:`lfcam.measure.noise.clipped_mean`).
    The model is the lenslet fit's own (the same trace, lattice crossing and pixel binning),
    its "lenslets" the lit pixels. The window stays fixed: the model and the data are compared
    on the same pixels wherever the source moves, so a window drawn about an answer a few %
    off costs information, not bias.

    Once a step is under :data:`PIXEL_REJACOBIAN_LOG`, the weights take the pixels' own
    photon gain (:func:`_local_gain`; the capture's is an upper bound, or unknown), and from
    then on pixels brighter than the model by over :data:`PIXEL_STRAY_Z` σ are left out, the
    steps going on without them: a neighbour's halo lands on other pixels of the same
    micro-images than this source's spots (its light comes from another direction), and the
    moments, which sum both, read it as this source's (χ²/dof 6-10 with such pixels, 0.3
    without).

    The answer is the mean of the minimum with the model's own pupil sample and of
    :data:`PIXEL_TURNS` turned samples' minima, each a linear step from it with its
    Jacobian; their standard error joins σ. Every fit draws the same sample, so on a given
    source its error is a bias, which the turned samples halve on average (not exactly: a
    turned sample's own full fit takes other re-weighting and stray-pixel paths).

    Returns the fit (σ from the weighted Jacobian, scaled up by χ²/dof where that is over
    1, or the sandwich estimate where that is larger; ``misfit`` NaN: the gates read the
    lenslet fit's; ``pixel_chi2`` the pixels' χ²/dof under ``noise`` as the capture states
    it, an upper bound, NaN where it has no gain), not ``ok`` (``poor-fit``, the lenslet
    answer then stands) where fewer than :data:`PIXEL_MIN_PIXELS` pixels are left, over
    :data:`PIXEL_MAX_STRAY` of them are stray (``pixel_chi2`` then counts them) or their
    χ²/dof is over :data:`PIXEL_MAX_CHI2`; None where the model lights too few pixels.
    """
    frame = SourceFrame(profile)
    source_mm = np.asarray(source_mm, dtype=np.float64)
    in_box = mom.labels >= 0
    if not in_box.any():
        return None
    look, rows, cols = _pixel_model(profile, geom, mom, in_box, PIXEL_WINDOW_RAYS)
    light = np.zeros(in_box.shape)
    light[rows, cols] = look.simulate(source_mm)[:, 0]
    top = float(light.max())
    if not top > 0:
        return None
    lit = light > PIXEL_WINDOW_SHARE * top
    if PIXEL_WINDOW_GROW:
        lit = cv2.dilate(lit.astype(np.uint8), np.ones((3, 3), np.uint8),
                         iterations=PIXEL_WINDOW_GROW).astype(bool)
    lit &= in_box
    if int(lit.sum()) < PIXEL_MIN_PIXELS:
        return None
    model, rows, cols = _pixel_model(profile, geom, mom, lit, PIXEL_RAYS)
    x0, y0 = mom.box[:2]
    raw = np.asarray(image[y0 + rows, x0 + cols], dtype=np.float64)
    floor = noise.floor_sigma  # > 0: the capture clips its noise at zero
    level = pedestal(image)
    data = raw if floor > 0 else raw - level
    q = frame.params(source_mm)
    m = model.simulate(source_mm)[:, 0]
    mm = float(m @ m)
    a = float(m @ (raw - level)) / mm if mm > 0 else 0.0
    if not a > 0:
        return None

    def variance(gain: float, light: np.ndarray) -> np.ndarray:
        # the pixels' noise at a model light (NoiseModel's read σ² + gain·I)
        return noise.read_sigma**2 + gain * np.clip(light, 0.0, None)

    gain = noise.gain
    if not gain > 0:  # no gain known: the pixels' own at the start (the model's misplaced
        #               spots add to it there: weights nearer uniform, a safe start)
        gain = _local_gain(data - clipped_mean(a * m, floor)[0], a * m, noise.read_sigma) or 0.0
    weight = 1.0 / np.sqrt(variance(gain, a * m) + 1e-300)
    steps = point_steps(profile, geom, lit_lenslets(mom))

    def residual(p: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # the weighted residual at p (model light m there), the reading's slope in light
        mean, slope = clipped_mean(math.exp(p[3]) * m, floor)
        return (data - mean) * weight, slope

    def residuals_at(qs: list[np.ndarray]) -> list[np.ndarray]:
        # the residuals at source parameters qs, p's intensity (one trace: fd_jacobian)
        return [residual(np.append(q_i, p[3]), m_i[:, 0])[0] for q_i, m_i in
                zip(qs, model.simulate_sets([frame.source(q_i) for q_i in qs]), strict=True)]

    def jacobian() -> np.ndarray:
        # distance and lateral columns by differences (jac3), the intensity's analytic
        return np.column_stack([jac3, -slope * math.exp(p[3]) * m * weight])

    p = np.append(q, math.log(a))
    r, slope = residual(p, m)
    use = np.ones(r.size, dtype=bool)  # the pixels not stray
    f = float(r @ r)
    jac3 = None  # the distance and lateral columns, taken again after a long step
    last = math.inf  # the last step's length (log distance)
    reweighted = False  # the weights are the pixels' own photon gain's (_local_gain)
    for _ in range(PIXEL_ITERATIONS):
        if jac3 is None or last > PIXEL_REJACOBIAN_LOG:
            jac3 = fd_jacobian(None, residuals_at, p[:3], r, steps)
        j_use = jacobian()[use]
        step = np.linalg.lstsq(j_use, -r[use], rcond=None)[0]
        # the least distance step worth a trace: a share of the fit's σ (log distance) there
        min_trial = PIXEL_MIN_TRIAL_SIGMA * _log_sigma(j_use, f, int(use.sum()))
        scale, improved = 1.0, None
        for _ in range(PIXEL_HALVINGS + 1):
            if abs(scale * float(step[0])) < min_trial:
                break
            p_new = p + scale * step
            m_new = model.simulate(frame.source(p_new[:3]))[:, 0]
            r_new, slope_new = residual(p_new, m_new)
            f_new = float(r_new[use] @ r_new[use])
            if f_new < f:
                improved = (p_new, m_new, r_new, slope_new, f_new)
                break
            scale *= 0.5
        if improved is not None:
            p, m, r, slope, f = improved
            last = abs(scale * float(step[0]))
        elif reweighted:
            break
        else:
            # at the minimum before the weights took the pixels' own gain: take it now (and
            # the stray pixels out) rather than stop with the capture's upper-bound weights,
            # whose χ²/dof then refuses a good fit (docs/distance.md, "A pixel fit that settles
            # before its re-weighting (stop 64)")
            last = 0.0
        changed = False  # the weights or the pixels changed: the steps go on
        if last <= PIXEL_REJACOBIAN_LOG and not reweighted:
            # near the minimum: the pixels' own photon gain, and the steps go on weighted by it
            # (without the stray pixels, below)
            reweighted = True
            gain = _local_gain(r / weight, math.exp(p[3]) * m, noise.read_sigma)
            if gain is not None:
                w_new = 1.0 / np.sqrt(variance(gain, math.exp(p[3]) * m) + 1e-300)
                ratio = w_new / weight
                weight, r = w_new, r * ratio
                jac3 = jac3 * ratio[:, None]
                f = float(r[use] @ r[use])
                changed = True
        stray = use & (r > PIXEL_STRAY_Z) if reweighted else None
        if stray is not None and stray.any():
            use &= ~stray
            f = float(r[use] @ r[use])
            changed = True
        if last < PIXEL_SETTLE_LOG and not changed:
            break
    jac = jacobian()
    n_use = int(use.sum())
    source, evaluations = frame.source(p[:3]), look.evaluations + model.evaluations
    stray_share = 1.0 - n_use / r.size
    # the pixels' χ²/dof at the capture's own noise (no gain known: no test), the stray pixels
    # counted where too many are stray
    counted = use if stray_share <= PIXEL_MAX_STRAY else np.ones_like(use)
    chi2_capture = (float(((r / weight)[counted] ** 2
                           / variance(noise.gain, math.exp(p[3]) * m)[counted]).sum())
                    / max(int(counted.sum()) - 4, 1)) if noise.gain > 0 else math.nan
    refused = LensletFit(source, math.nan, math.nan, evaluations, False, RegionStatus.POOR_FIT,
                         pixel_chi2=chi2_capture)
    if n_use < PIXEL_MIN_PIXELS or stray_share > PIXEL_MAX_STRAY:
        return refused
    chi2 = f / max(n_use - 4, 1)
    j_use, r_use = jac[use], r[use]
    # σ: the weighted Jacobian's, scaled by χ²/dof where that is over 1, or the sandwich
    # (JᵀJ)⁻¹ Jᵀ diag(r²) J (JᵀJ)⁻¹ where more (weights that misjudge the noise's trend); a
    # Jacobian with a wild column gives no finite σ: refused
    try:
        with np.errstate(over="ignore", invalid="ignore"):
            inv = np.linalg.inv(j_use.T @ j_use)
            sandwich = inv @ ((j_use * (r_use * r_use)[:, None]).T @ j_use) @ inv
    except np.linalg.LinAlgError:
        return refused
    var = max(float(inv[0, 0]) * max(1.0, chi2), float(sandwich[0, 0]))
    if not (chi2 <= PIXEL_MAX_CHI2 and var > 0 and math.isfinite(var)):
        return refused
    # The pupil sample's own error: every fit draws the same sample, so on a given source its
    # error is a bias (+0.18 % on system 1's 3 100 mm source at 49 % of the field behind a
    # 1 m focus, over 20 draws; none at 4 × the rays). The minima of PIXEL_TURNS turned
    # samples (one linear step each from this one's, with its Jacobian) and this one's: their
    # mean is the answer, their standard error joins σ (docs/distance.md, "The pixel fit's
    # pupil sample, turned (stop 65)").
    turns = [np.zeros(4)]
    for k in range(1, PIXEL_TURNS + 1):
        # (the same pixels: the fit model's own "lenslets")
        turned = LensletModel(profile, geom, model.mom, PIXEL_RAYS,
                              phase=2.0 * math.pi * k / (PIXEL_TURNS + 1))
        r_t = residual(p, turned.simulate(frame.source(p[:3]))[:, 0])[0]
        turns.append(np.linalg.lstsq(j_use, -r_t[use], rcond=None)[0])
        evaluations += turned.evaluations
    q_answer = p[:3] + np.mean(turns, axis=0)[:3]
    if PIXEL_TURNS:
        var += float(np.var([t[0] for t in turns], ddof=1)) / len(turns)
    dist = math.exp(_log_distance(q_answer))
    ok = not _at_far_bound(q_answer)
    return LensletFit(frame.source(q_answer), math.nan, dist * math.sqrt(var), evaluations, ok,
                      "" if ok else RegionStatus.NO_SOLUTION, polished=True,
                      pixel_chi2=chi2_capture)


def measure_lenslet(profile: CameraProfile, geom: Geometry, image: np.ndarray,
                    region: Region, noise: float,
                    accept: Callable[[float, float], bool] | None = None,
                    others: Sequence[Region] = (),
                    light: np.ndarray | None = None,
                    start: Measurement | None = None) -> Measurement:
    """Lenslet-statistics fit of one region (module docstring).

    Parameters
    ----------
    profile : CameraProfile
    geom : Geometry
    image : (H, W) float array
    region : Region
    noise : float
    accept : callable, optional
        ``accept(distance_mm, sigma_mm)``: whether an answer that certain is enough for the
        caller: a line's before its refit (:func:`fit_lenslet_line`), a point's before its
        polish (:func:`point_fit_stages`); without it every line is refitted and every point
        polished where their settled tests ask.
    others : sequence of Region, optional
        The capture's other regions near this one (:func:`lfcam.measure.regions.nearby_regions`):
        their lenslets inside this region's box are left out of its data and models
        (:func:`data_moments`' ``exclude``). In a crowded capture a neighbouring blur's
        lenslets in the box put misfits of 0.24-0.50 on a point whose own light the model
        fits to 0.04 (docs/distance.md, "Other regions' lenslets left out of a box (stop 60)").
    light : (K, 4) array, optional
        Other sources' fitted light on this region's lenslets, in the layout of
        :func:`region_moments` (``region``, ``others``), taken from the data's moments before
        the fit: a touching blur's light past the band
        (:func:`lfcam.measure.overlap.neighbour_light`).
    start : Measurement, optional
        An earlier ``lenslet`` answer of this region (:attr:`Measurement.fitted_mm`), the
        refit's one start: a line is refitted as a line from its ends, with no point fit,
        distance scan or race (:func:`fit_lenslet_line`'s ``start_q``); a point's fit starts
        from its source, with no scan or summary matching, and goes on as any point's
        (docs/distance.md, "A refit from the first answer (stop 72)"). A line's answer keeps
        ``start``'s ``model_misfit`` (the point fit's, which the refit does not run).

    Returns
    -------
    Measurement
    """
    # the poor-fit gate and the line trigger are relative to the region's own noise
    # (lfcam.measure.noise); a fit whose misfit comes near either is polished
    # once: the noise misfit, the point and the line fit
    mom = region_moments(geom, image, region, others)
    if light is not None:
        if light.shape != mom.data.shape:
            raise ValueError(f"light {light.shape} does not match the region's moments "
                             f"{mom.data.shape}")
        data = mom.data - light
        mom = dataclasses.replace(mom, data=data, norm=float(np.sqrt((data * data).sum())))
    noise_model = capture_noise(image, geom.lmap, geom.pitch_px)
    nm = noise_model.moments_misfit_of(mom.noise_sums, mom.norm)
    limit = poor_fit_limit(nm, POOR_FIT)
    noise_trigger = line_trigger(nm, LINE_TRIGGER, LINE_NOISE_FACTOR)

    def trigger_of(model_misfit: float) -> float:
        # the point misfit over which a line is tried: over the noise's trigger, and over
        # LINE_MODEL_FACTOR × what the point models' own ray samples leave (noise-free
        # points leave up to 1.1 × that, lines fitted as points 2.9-300 ×: docs/distance.md,
        # "A line trigger over the point models' own noise")
        return max(noise_trigger, LINE_MODEL_FACTOR * model_misfit)

    def worth_a_line(point_misfit: float, trigger: float) -> bool:
        # over the trigger, and not within the region's noise: a point that leaves no more
        # than its noise misfit leaves a line's two more parameters nothing to win by
        # LINE_GAIN (the trigger's cap lets such dim points try lines that cannot win)
        return point_misfit > trigger and not point_misfit <= LINE_WITHIN_NOISE * nm

    def gates(model_misfit: float) -> tuple[float, float]:  # polish_above, bound_above
        trigger = trigger_of(model_misfit)
        return POLISH_NEAR_GATE * min(limit, trigger), trigger

    def beats(point_misfit: float) -> float:  # the misfit a line must stay under to win
        return line_beats(point_misfit, nm, LINE_GAIN)

    frame = SourceFrame(profile)
    start_q = None
    if start is not None and len(start.fitted_mm) == 2:
        # a line stays a line: refitted from its ends, as useful as any fit under the limit
        line = fit_lenslet_line(profile, geom, image, region, useful_below=limit, mom=mom,
                                accept=accept, start_q=frame.fitted_params(start.fitted_mm))
        if not line.ok:
            return Measurement.failed(line.reason or RegionStatus.POOR_FIT, geom.d_in_mm,
                                      kind="line")
        return _line_answer(profile, geom, line, limit, nm, start.model_misfit)
    if start is not None and len(start.fitted_mm) == 1:
        start_q = frame.fitted_params(start.fitted_mm)

    tried: list[LensletFit] = []

    def line_for(point: LensletFit) -> LensletFit:
        # the line fit that could replace a point, tried once a region: a later call (after
        # the point's fine stage, or its polish) returns the first try
        if not tried:
            tried.append(fit_lenslet_line(profile, geom, image, region, point,
                                          useful_below=min(beats(point.misfit), limit),
                                          mom=mom, accept=accept))
        return tried[0]

    stages = point_fit_stages(profile, geom, image, region, mom=mom, gates=gates,
                              early=LINE_AT_COARSE, accept=accept, noise_misfit=nm,
                              start_q=start_q)
    fit = next(stages)  # the fine fit, before its polish and σ profile (or the coarse one)
    if fit.coarse:
        # On the cells the point's coarse stage is read first. A line's blur leaves a point's
        # misfit where it is through the fine steps, so a line that wins there by more than
        # any polish could take back needs no fine point fit (docs/distance.md, "A line tried
        # at the point's coarse stage (stop 47)"). One that does not is kept (line_for) for
        # the tests below, which compare its misfit with the fine fit's.
        if fit.ok and worth_a_line(fit.polish_floor, trigger_of(fit.model_misfit)):
            line = line_for(fit)
            if line.ok and line.misfit < beats(fit.polish_floor):
                stages.close()
                return _line_answer(profile, geom, line, limit, nm, fit.model_misfit)
        fit = next(stages)
    model_misfit = fit.model_misfit  # (the fine fit's look: the answer carries it)
    trigger = trigger_of(fit.model_misfit) if fit.ok else noise_trigger
    if not fit.ok and fit.reason == RegionStatus.NO_SOLUTION and fit.misfit > trigger:
        # a point fit run out to the far bound that explains the data no better than the
        # trigger: a line is tried before the region is given up (its own distance scan
        # finds its start; system 2's lines at 380 mm, 60-80 % of the field, whose point fit
        # ran out there: docs/distance.md, "Large point blurs on the cells (stop 44)")
        stages.close()
        line = line_for(dataclasses.replace(fit, ok=True))
        if line.ok and line.misfit < beats(fit.misfit):
            return _line_answer(profile, geom, line, limit, nm, model_misfit)
        return Measurement.failed(fit.reason, geom.d_in_mm)
    if fit.ok and worth_a_line(fit.polish_floor, trigger):
        # no polish can bring this misfit under the trigger, so a line will be tried: it is
        # tried before the point is finished, and when it wins by more than any polish could
        # take back (fit.polish_floor), the point's polish and σ profile are not needed
        line = line_for(fit)
        if line.ok and line.misfit < beats(fit.polish_floor):
            stages.close()
            return _line_answer(profile, geom, line, limit, nm, model_misfit)
        if ((not line.ok or line.misfit >= beats(fit.misfit))
                and fit.polish_floor > limit):
            # the line cannot win even against the unpolished point (the polish only lowers
            # its misfit), and no polish brings the point under the poor-fit limit
            stages.close()
            return Measurement.failed(RegionStatus.POOR_FIT, geom.d_in_mm)
    if fit.ok:
        fit = next(stages)
    if not fit.ok:
        return Measurement.failed(fit.reason, geom.d_in_mm)
    # a line is tried on the misfit alone, whatever the region's shape: F/2 coma and
    # vignetting stretch off-axis points into regions the finder calls `line` (elongation up
    # to 2.3 at 80 % of system 1's half-field) whose point fits leave 0.17-0.73 × the
    # trigger; the 126 rectangular grid lines logged leave 1.2 × it or more as a point, and
    # all 231 grid lines read the same without the shape rule (docs/distance.md,
    # "Line-shaped point regions (stop 49)")
    if worth_a_line(fit.misfit, trigger):
        # a line changes the answer only below both: a win over the point, and an `ok` fit
        line = line_for(fit)
        if line.ok and line.misfit < beats(fit.misfit):
            return _line_answer(profile, geom, line, limit, nm, model_misfit)
    if not fit.misfit <= limit:
        return Measurement.failed(RegionStatus.POOR_FIT, geom.d_in_mm)
    if PIXEL_POLISH and _uncertain(profile, fit, accept):
        # the moments left this answer uncertain: its lit pixels hold more (a dim blur
        # behind focus: docs/distance.md, "The lit pixels of an uncertain point (stop 63)")
        better = pixel_polish(profile, geom, image, mom, fit.source_mm, noise_model)
        if better is not None and better.pixel_chi2 > PIXEL_POINT_CHI2:
            # no point explains these pixels, even at the capture's upper-bound noise: a
            # line, or no distance (a dim 1.5 mm line at 3.5 m, within its moments' noise,
            # read as a spot 38 % long: docs/distance.md, "A point the pixels refuse")
            line = line_for(fit)
            if line.ok and line.misfit < beats(fit.misfit):
                return _line_answer(profile, geom, line, limit, nm, model_misfit)
            return Measurement.failed(RegionStatus.POOR_FIT, geom.d_in_mm)
        if better is not None and better.ok and _agrees(profile, fit, better):
            fit = dataclasses.replace(fit, source_mm=better.source_mm,
                                      sigma_distance_mm=better.sigma_distance_mm)
    return point_measurement(profile, geom.d_in_mm, fit.source_mm, fit.sigma_distance_mm,
                             SIGMA_FLOOR_REL, misfit=fit.misfit, noise_misfit=nm,
                             model_misfit=model_misfit, method="lenslet")


def _agrees(profile: CameraProfile, lenslet: LensletFit, pixel: LensletFit) -> bool:
    """Whether the pixel answer lies within :data:`PIXEL_AGREE_SIGMAS` of the lenslet one's
    σ (log distance). The pixels ask more of the calibration than the moments: a micro-image
    model off by a fraction of a pixel moves them where it does not move the moments (at 80 %
    of system 1's field, the white's centres put a bright point's pixel answer 3.1 % long at
    σ 0.06 %, the renderer's centres +0.07 %, the moments' answer −0.35 %: 17 lenslet σ
    apart); over 30 draws of the 12-source captures no pixel answer lay over 7.1 lenslet σ
    from its lenslet answer (776 answers), and every one over 3 was the nearer the truth."""
    z = profile.main_lens.front_vertex_z_mm
    d_l, d_p = z - float(lenslet.source_mm[2]), z - float(pixel.source_mm[2])
    if not (d_l > 0 and d_p > 0):
        return False
    return abs(math.log(d_p / d_l)) <= PIXEL_AGREE_SIGMAS * lenslet.sigma_distance_mm / d_l


def _uncertain(profile: CameraProfile, fit: LensletFit,
               accept: Callable[[float, float], bool] | None) -> bool:
    """Whether a point's lenslet answer is less certain than :data:`PIXEL_POLISH_ABOVE` (its
    σ with :data:`SIGMA_FLOOR_REL` in quadrature, relative) and, with ``accept``, not
    accepted: :func:`measure_lenslet` then refits it on its pixels (:func:`pixel_polish`)."""
    dist = profile.main_lens.front_vertex_z_mm - float(fit.source_mm[2])
    sigma = math.hypot(fit.sigma_distance_mm, SIGMA_FLOOR_REL * dist)
    if not sigma > PIXEL_POLISH_ABOVE * dist:  # (a NaN σ is no answer to refit)
        return False
    return accept is None or not accept(dist, sigma)


def _line_answer(profile: CameraProfile, geom: Geometry, line: LensletFit, limit: float,
                 noise_misfit: float, model_misfit: float) -> Measurement:
    """The measurement of a line that won over the point: ``poor-fit`` over ``limit``
    (``model_misfit``: the point fit's, :attr:`Measurement.model_misfit`)."""
    if not line.misfit <= limit:
        return Measurement.failed(RegionStatus.POOR_FIT, geom.d_in_mm, kind="line")
    return line_measurement(profile, geom.d_in_mm, line.ends_mm, line.sigma_distance_mm,
                            misfit=line.misfit, noise_misfit=noise_misfit,
                            model_misfit=model_misfit, method="lenslet")
