"""Every tunable of the engine that is not a setting (``service.settings.EngineSettings``), in
one place, grouped by the step of the chain it tunes. Why each value is what it is, with the
figures that chose it: docs/decisions.md, under the step's heading."""

from __future__ import annotations

# --- 0. Surroundings: the support plane and stray points (docs/decisions.md#surroundings) ---------
SURROUNDINGS_SAMPLE = 1024  # decisions are made on a sample of this many points
# a part in a bin (docs/decisions.md#a-part-in-a-bin), looked for where no reading fits
BIN_BELOW = 0.6  # this well (fit x coverage): the floor, the largest of BIN_FLOORS planes of at
BIN_FLOORS = 2  # least BIN_PLANE_SHARE of the sample that has walls, at most BIN_WALLS planes
BIN_PLANE_SHARE = 0.06  # upright on it, each reaching BIN_REACH times as far from the part's
BIN_WALLS = 4  # centre as the part does, with the part on its inner side (ONE_SIDE); the part:
BIN_REACH = 1.2  # the largest group left of BIN_PART_POINTS of the sample that is not flat
BIN_PART_POINTS = 24  # (BIN_FLAT: a piece of wall is), with those within BIN_JOIN of its
BIN_FLAT = 0.05  # radius; a noisy sensor's floor or wall lies within BIN_BAND of its fitted
BIN_JOIN = 1.0  # thicknesses (what else is looked for lies beyond)
BIN_BAND = 2.0
BIN_ACCEPT = 0.87  # an answer of a bin's reading is a "match" from this confidence on
PLANE_SHARE = 0.2  # a support plane holds at least this share of the points ...
PLANE_SHARE_BLIND = 0.5  # ... this share, when the viewpoint is not known
PLANE_REACH = 1.5  # ... reaches this many times the rest's radius from the rest's centroid
ONE_SIDE = 0.95  # ... has this share of the rest on one side of it
BEYOND = 0.5  # ... has this share of its points beyond the part's footprint
AROUND = 9  # ... in at least this many of 12 directions around it
PLANE_ITERATIONS = 96  # RANSAC draws for the largest plane
PLANE_SCORED = 256  # points the candidate planes are scored on
PLANE_SPACINGS = 1.5  # plane inliers lie within this many spacings of it
THICKNESS = 4.0  # a table: within this many robust standard deviations of its fitted plane
LINK_SPACINGS = 3.0  # neighbours closer than this many spacings are one group
STRAY_SHARE = 0.02  # a group of less than this share of the points ...
STRAY_GAP = 10.0  # ... this many spacings from any larger group is stray

# --- 3-4. Grid and classify (docs/decisions.md#classify) ------------------------------------------
POOL = 2  # eq. (4)'s input: grid bins pooled per side after smoothing
VIEW_POOL = 4  # nearest-view features: the smoothed grid pooled 4x4 (to 16x16 = 256 values)
VIEW_POINTS = 512  # a rendered view's grid is made of at most this many of its points
FIRST_LEAD = 2.0  # eq. (4) is sure of its first choice at this many times the next score

# --- 5. Hypothesise (docs/decisions.md#hypothesise) -----------------------------------------------
VIEWPOINT_AGREEMENT_DEG = 50.0  # a view hypothesis's camera within this of the viewpoint's
ROUND_SPREADS = 0.1  # two principal spreads this close: a round or square section ...
ROUND_TURN_DEG = 45.0  # ... whose principal-axes matches are also turned by every this much
QUICK_POINTS = 24  # observed and expected points of the quick look that screens hypotheses
WHOLE_SCREENED = 4  # principal-axes hypotheses verified in the whole-part pass (4 sign flips)

# --- 6. Verify (docs/decisions.md#verify) ---------------------------------------------------------
EXPECTED = 128  # expected-visible points drawn per rendered view for coverage
OCCUPANCY_SPACINGS = 1.5  # the occupancy's voxel is at least this many observed spacings
PATCH_SPACINGS = 2.5  # a sample's tangent patch reaches this many sample spacings
FIELD_RESOLUTION = 40  # distance-field voxels along the reference's longest side
FIELD_MARGIN = 0.3  # the field reaches this share of the scale beyond the bounding box

# --- 7. Refine (docs/decisions.md#refine) ---------------------------------------------------------
WHOLE_REFINED = 2  # hypotheses refined in each whole-part pass
# a pass's best hypothesis verifying this well is refined alone first (an answer's mostly
# refines to excellent, which ends the pass); below, the pass's are refined together
ALONE_FROM = 0.6
ENOUGH_BEHIND = 0.8  # a hypothesis this far below an excellent refined one is not refined
FAR_BELOW = 0.5  # nor one below this share of the best hypothesis before refining
PER_PART = 2  # hypotheses refined of one part in a pass
FIRST_REFINED = 1  # hypotheses of eq. (4)'s sure first choice refined in any case
RESCUE_BELOW = 0.7  # no refined fit x coverage this high: more parts are rescued
RESCUE_EACH = 2  # hypotheses refined of each rescued part
# a cloud's hidden share (visibility.hidden_share): of this many points, cells this many point
# spacings wide, nearer by this many spacings (docs/decisions.md#a-whole-parts-cloud)
HIDDEN_POINTS, HIDDEN_CELL, HIDDEN_DEPTH = 512, 1.5, 4.0
# a whole part's cloud fitting less than this after its principal axes is not finished (flips,
# near-symmetries): right ones reached it at 0.70-0.995, others at 0.31-0.66 (measured)
WHOLE_FINISHED = 0.6
MORE_VIEWS_BELOW = 0.6  # no refined fit x coverage this high: more parts' views are searched
SURFACE_NEIGHBOURS = 8  # a sample's neighbours searched when correcting the field's answer
BEHIND = 1.0  # a point more sample spacings than this behind a tangent plane is not on it
CLOSE_RAD, CLOSE = 0.01, 0.5  # steps this small switch to the corrected nearest samples
BACK_FACING = 0.2  # a sample whose normal's cosine to the camera is under -this faces away
NORMAL_NEIGHBOURS = 16  # points in the plane fitted for an estimated normal
# near-symmetries: turned poses screened on the field, then on the corrected distance
NEAR_PRESCREENED = 32
NEAR_SCREENED = 8
SCREEN_ALIKE = 1.5  # a turned pose this much farther before refining is not refined
RESIDUAL_ALIKE = 1.15  # a turned pose this much farther from the surface is no alternative

# --- 8. Decide (docs/decisions.md#decide) ---------------------------------------------------------
DIFFERENT_DEG = 10.0  # poses this far apart (symmetry accounted for) are different answers
ALIKE = 0.9  # ... and fit alike within this share of the best's fit x coverage
# a registered look-alike fitting within this share of the winner makes the label a guess
# (a full cloud of either of a pair fits the other 0.83-0.95; docs/decisions.md#either-way)
LOOK_ALIKE = 0.97
MAX_ALTERNATIVES = 3
# another pose closer than this share of the scale is no doubt: the answer would still be
# precise (ADD-S under 0.02 of the diameter) were it the truth
RIGHT_EITHER_WAY = 0.02
FLAT = 0.03  # an observation this flat (smallest over largest principal spread) is one face
# ... this thin (middle over largest spread), one line: no turn about it can be told
LINE = 1e-3
POOR_FIT = 0.8  # an answer whose part holds less of the cloud may be a cloud in other units

# --- Registration: what one camera sees (docs/decisions.md#registration) --------------------------
HPR_LOG_RADIUS = 2.8  # hidden-point removal's flipping sphere: 10**this times the extent

# --- Whole frames: supports, segments, instances (docs/decisions.md#detect) ----------------------
THIN_PER_SCALE = 20  # a frame is thinned to a voxel of the smallest part's scale over this
SUPPORT_SAMPLE = 2048  # points the support planes are found on ...
SUPPORT_POINTS = 80_000  # ... and judged on: a coarser copy of the frame, at most this many
SUPPORT_SHARE = 0.03  # a support holds at least this share of the frame's points ...
LATER_SHARE = 0.1  # ... a later one (a wall) this share of the points left ...
CARRIED_POINTS = 50  # ... carrying more points than this, unless it is a wall
BEHIND_SHARE = 0.2  # ... and has less than this share of what lies over it behind it
SLAB_SHARE = 0.1  # a support's slab (a table's edge, a bin's floor) is this thin for its reach
# a bin's floor lies this level with the table it stands on; parts' tops in one plane tilt more
# (docs/decisions.md#a-bins-floor-level-with-the-table)
FLOOR_DEG = 2.0
SUPPORT_REACH = 1.5  # ... or reaches this many times the largest part's scale (no face does)
RAISED_SHARE = 0.2  # a plane over the first, parallel, this share of its points: a table
PART_EXTENTS = 2.0  # the parts on a support are at most this many times what is left's extent
WALL_REACH = 1.2  # ... or is a wall reaching this many times the largest part's scale ...
SUPPORT_CONNECTED = 0.8  # ... a later one with this share of its cells in one patch
WALL_DEG = 20.0  # ... upright on the first support, within this many degrees
BOUND_CELLS = 3.0  # a bin's wall comes within this many support cells of its floor ...
BOUND_STRAYS = 0.02  # ... with no more than this share of the floor on its far side
SUPPORT_CELLS = 4.0  # what lies over a plane: over its cells of this many pixel footprints
SUPPORT_SPACINGS = 1.5  # its points lie within this many pixel footprints of it ...
SUPPORT_NOISE = 0.003  # ... plus this share of their range (the sensor's depth noise)
RIM_NOISES = 3.0  # a part's lower rim in that band: this many times the measured noise over it
RIM_STEPS = 3  # ... given back within this many pixels of a point kept, through its rim
MAX_SUPPORTS = 6  # a bin's floor and four walls, and the table beside it
MAX_PLANES = 10  # planes tried as supports, parts' faces among them
SUPPORT_ITERATIONS = 400  # RANSAC draws for a support plane (a bin's floor: a fifth of the rest)
LEVEL_CONNECTED = 0.4  # a bin's floor, parts lying on it, with this share of its cells in one patch
BAND_INSIDE = 2.0  # a bin's walls stand from this many support cells inside its floor's outline ...
BAND_OUTSIDE = 0.15  # ... to this share of the floor's reach outside it ...
BAND_STANDING = 0.1  # ... where points rise over the floor by this share of its reach ...
BAND_SIDE = 0.01  # ... along three sides, each as many as this share of the floor's points
BAND_TRIM = 0.002  # the outline: the floor's points but this share on each side
LINK_FOOTPRINTS = 3.0  # neighbouring pixels this many footprints apart are one segment ...
LINK_NOISE = 0.004  # ... plus this share of their range
FINER_LINKS = ((2.0, 0.002), (1.2, 0.0005))  # a failed region split again: footprints, share
# ... then at a crease: a valley whose sides, this many pixels to either side, face each other
# with normals (fitted on NORMAL_PIXELS squares) this many degrees apart; 30 and 45 split more
# and matched more wrong (docs/decisions.md#touching-parts-split-at-a-crease)
CREASE_PIXELS = 2
CREASE_DEG = 60.0
NORMAL_PIXELS = 5
MIN_SEGMENT = 60  # a segment (or what is left of it) of fewer points is not searched
MIN_EXPLAINED = 40  # an instance explains at least this many of its segment's points
MATCH_POINTS = 150  # ... and a "match" this many (fewer were right 8 times in 244)
CHAIN_AGREES = 0.5  # ... and the chain's own confidence for its points at least this
MAX_TRIES = 6  # searches of a segment and its pieces (docs/decisions.md#a-segments-searches-six)
PIECE_CELLS = 4  # what is left of a segment is searched in pieces: cells this many spacings wide
# a region's groups of such cells smaller than a segment, beyond its bulk's radius, are asked
# without, where they hold this share of it at most (docs/decisions.md#a-regions-strays)
STRAYS = 0.1
SEVERAL = 2  # a part matched this often in a frame is looked for again, told it alone ...
HELD_FROM = 0.7  # ... or refused this sure (docs/decisions.md#several-likely-instances)
CLAIM_TOLERANCE = 1.5  # an instance claims the points within this many tolerances of it
KEEP_SHARE = 0.5  # an instance left with less of its claim after the global check goes
JOIN_PIXELS = 3  # segments where nothing was found are joined with those this near
INSTANCE_FLOOR = 0.3  # an instance less confident than this is not listed (uncertain above it)
AROUND_SCALES = 0.5  # what no instance explains within this share of a part's scale is around it
AROUND_SAMPLE = 512  # ... measured from this many of its points at most
AROUND_DOUBT = 0.2  # an instance not a match with this share of its points around it says so
SEED_SPACING = 0.35  # a part's views are placed at seeds this many scales apart ...
MAX_SEEDS = 24  # ... at most this many over a segment
TEMPLATE_ANGLES = 12  # ... turned about the line of sight this many times
TEMPLATE_POINTS = 24  # ... screened on this many of each view's expected points
TEMPLATE_TOLERANCE = 0.1  # ... within this share of the part's scale
TEMPLATE_REFINED = 16  # the best placed views refined (per seed kept, then overall)
TEMPLATE_PARTS = 3  # parts whose views are placed over a segment where the chain found none
TEMPLATES_ASKED = 2  # ... the chain asked about what each part's best few placed explain
PINHOLE_RESIDUAL_PX = 0.75  # a frame whose pixels fit a pinhole this well has a depth image
PINHOLE_POINTS = 4096  # ... fitted on about this many of its points, evenly through it
PIXEL_PAIRS = 65_536  # a frame's pixel angle: the median over about this many neighbours
DIRECT_PAIRS = 0.9  # ... from next pixels where this share of the pairs are; else, where
SPARSE_GAP = 4  # pixels are missing in a pattern, pairs in a row at most this many apart
SPARSE_WINDOW, SPARSE_SAMPLE = 8, 512  # a frame's share of pixels with a point: windows, samples
BLOCKS_HELD = 0.75  # a thinned grid's first pixels holding less of its blocks with a point: filled
RANK_EVERY, RANK_ANGLES, RANK_SEEDS = 4, 8, 3  # ... which parts: every 4th view, 8 turns, 3 seeds
TEMPLATE_SIZES = (0.25, 1.15)  # ... of a scale this share of the segment's radius
NOISE_TOLERANCES = 2.0  # a fit's tolerance is at least this many times the sensor's noise
SENSOR_NOISE = 0.0015  # the depth noise's share of the range where no support measures it
SEED_SAMPLE = 2048  # seeds are spread over a sample of this many of a segment's points
TEMPLATE_ICP_POINTS = 384  # a placed view is refined on this many of the points around it
SEGMENT_POINTS = 4096  # the chain answers a segment from this many of its points at most
SEGMENT_RESCUED = 8  # ... trying this many more parts where none fits (a lone cloud: 4)
THROUGH_DOUBT = 0.1  # an instance the camera saw through more than this is doubted
# ... and posed again at its part's near turn the camera sees through least, below this share
TURNED_THROUGH = 0.5
# of look-alikes fitting alike in a frame, one explaining this much more of the region's points,
# seen through no more than this much more, is told apart (docs/decisions.md#look-alikes-in-a-frame)
ALIKE_EXPLAINED, ALIKE_THROUGH = 0.03, 0.05
# ... or one whose claim holds this share of points (and this many) the other's surface at its
# pose does not come near, this many times as many as the other's such points: a face the other
# lacks, in view (docs/decisions.md#a-face-one-look-alike-lacks)
ALIKE_FACE_SHARE, ALIKE_FACE_POINTS, ALIKE_FACE_RATIO = 0.02, 10, 3.0
# ... counted only against a pose of the other the camera sees through no more than this much
# more (docs/decisions.md#a-face-one-look-alike-lacks)
ALIKE_FACE_THROUGH = 0.3
THROUGH_WEIGHT = 6.0  # a refined placed view: what the camera saw through counts this much
DUPLICATE_GAP = 0.1  # two instances of a part this close (share of its scale) are one
FRAGMENT = 0.3  # a region narrower than this share of the smallest part's scale is a fragment
FRAGMENTS_ADD = 0.03  # a failed segment is searched again with the fragments by it adding this
JOIN_SCALES = 1.2  # segments are joined only into a region no wider than this many scales ...
MAX_JOINS = 6  # ... and only so many times a frame
TEMPLATE_FIT = 0.8  # a region whose best part explains less of it may hold several ...
WIDER = 1.25  # ... as may one wider than this many times that part's scale
FINISH_POINTS, FINISH_ITERATIONS = 1024, 20  # an instance's pose finished on its claim
# a doubted instance at least this confident is turned over (``Scan.turned_over``), each turn
# refined on this many of its points; a turn kept explains all but this share of what it did
# (docs/decisions.md#turned-over)
TURNED_FLOOR, TURNED_POINTS, TURNED_EXPLAINED = 0.2, 256, 0.01
TEMPLATE_POOL = 8  # more parts than this plausible: no views are placed

# --- Symmetry: finding a part's turns (docs/decisions.md#symmetry) ---------------------------
TOLERANCE = 0.015  # share of the scale
SPACINGS = 0.5  # or this many sample spacings, if more
SHARE = 0.97  # of the leave-one-out share within the tolerance
FAR, FAR_RATIO, FAR_EXTRA = 3.0, 1.5, 0.005  # points beyond FAR tolerances: at most so many more
REVOLUTION_ANGLES_DEG = (37.0, 101.0, 163.0, 229.0, 293.0)
# a round surface exported as facets (a CAD mesh's chords) is off its turned self by the chord's
# sag between facets: about 2 % of the scale for a ring of 16 facets; turns about a revolution's
# axis are held to twice the tolerance (a gear's teeth, half a pitch off, still fail by far)
REVOLUTION_SLACK = 2.0
MAX_FOLD = 8
RANDOM_STARTS = 12
SAME_DEG = 5.0  # two found rotations this close are one
SYMMETRY_QUICK, SYMMETRY_QUICK_POINTS = 8, 128  # a start's first refinement: iterations, points
QUICK_SLACK = 0.05  # the share it may fall short of the reference's own within FAR tolerances
MAX_GROUP = 120  # the largest discrete group looked for (a 60-tooth gear, both ways up)
NEAR = 0.8  # a turn keeping this share of the reference's own within the tolerance nearly fits
NEAR_TURN_DEG = 10.0  # about a nearly round axis, the answer is tried at turns this far apart
MAX_NEAR = 48
# the answer is also tried turned this far either way about each near turn's axis, from itself
# and from each near turn: point-to-plane ICP hardly turns a nearly round part about its axis
# (only a hole's wall or a notch resists, and the robust kernel drops those while they lie
# farther off than the noise), so a start 5 degrees off stays there (the KUKA flange)
FINE_DEG = NEAR_TURN_DEG / 3
ROUND_TURNS = 3  # near turns about one axis that make it nearly round
DRIFT = 0.1  # share of the scale a refined symmetry may move the sample's centroid (its own error)

# --- Rendered views of a registered part (docs/decisions.md#rendered-views) --------------------
CAMERA_DISTANCE = 6.0  # scales from the centroid to a view's camera
PIXEL_SPACINGS = 2.0  # a depth-buffer pixel spans this many surface-sample spacings
DEPTH_SPACINGS = 3.0  # a point this many spacings behind a pixel's nearest sample is hidden
CLOUD_SPACINGS = 2.5  # a cloud's spacing, in median distances between neighbours
FACING = 0.3  # a cloud's view keeps the points whose normal's cosine to its camera exceeds
MAX_BUFFER = 1 << 22  # pixels of a dense depth buffer; a larger image is sorted instead
