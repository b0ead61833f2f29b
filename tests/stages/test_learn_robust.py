"""The learning loop under gross errors (issue 13): the local screen, bounded CV costs, the loop end to end."""

import cv2
import numpy as np
import pytest
from fluorocal.stages.learn import LearnParams, calibrate, cross_validate_k
from fluorocal.stages.learn.robust import local_screen
from scipy.spatial import KDTree

NOISE_PX = 0.05


def _radial(xy, size=512.0):
    """A strong smooth field: up to ~4 px at the corners, like the simulator's strong distortion."""
    c = (size - 1) / 2
    d = (xy - c) / c
    return 2.0 * d * np.sum(d**2, axis=1, keepdims=True)


def _gross(rng, n, fraction=0.05):
    """Rows and displacements of ``fraction`` of ``n`` observations moved by 3-15 px in a random direction."""
    rows = rng.choice(n, int(fraction * n), replace=False)
    length, angle = rng.uniform(3, 15, len(rows)), rng.uniform(0, 2 * np.pi, len(rows))
    return rows, length[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])


def test_local_screen_catches_gross_errors_and_keeps_a_strong_smooth_field():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 511, (3000, 2))
    r = _radial(xy) + rng.normal(0, NOISE_PX, xy.shape)
    rows, moved = _gross(rng, len(xy))
    r[rows] += moved
    screen = local_screen(xy, r, np.full(xy.shape, NOISE_PX**2), chi2=LearnParams().screen_chi2)
    clean = np.ones(len(xy), bool)
    clean[rows] = False
    # every gross error is >= 3 px = 60 sigma off its neighbours' median: all caught
    assert not screen.keep[rows].any()
    # the field's curvature over 16 neighbours (~10 px) is far below the screen's ~20 sigma: clean ones stay
    # (measured: all 2850 kept)
    assert screen.keep[clean].mean() > 0.999


def test_bounded_cv_cost_chooses_k_as_on_clean_data():
    rng = np.random.default_rng(1)
    xy = rng.uniform(0, 511, (3000, 2))
    r = _radial(xy) + rng.normal(0, NOISE_PX, xy.shape)
    var = np.full(xy.shape, NOISE_PX**2)
    kw = dict(k_grid=(4, 8, 16, 32, 64, 128), n_folds=10, seed=0)
    clean = cross_validate_k(xy, r, var, **kw)
    rows, moved = _gross(rng, len(xy), 0.01)
    bad = r.copy()
    bad[rows] += moved
    # a gross error costs up to (15 / 0.05)^2 = 9e4 out of fold against ~2 per clean one: unbounded,
    # 1 % of them decide k (measured: 32 against 4); bounded (at screen_chi2 x the noise scale, as the
    # loop does), every candidate pays alike
    capped = cross_validate_k(xy, bad, var, cost_cap=LearnParams().screen_chi2, **kw)
    assert capped.k == clean.k
    # the RMS of the observations below the bound: measured 0.085 against 0.073 px clean (the gross errors
    # still pull their clean neighbours' out-of-fold means; in the loop the screen removes them first),
    # unbounded 0.69 px
    assert capped.cv_rms_px == pytest.approx(clean.cv_rms_px, rel=0.25)


def test_screen_threshold_is_validated():
    from fluorocal.stages.errors import InputError

    with pytest.raises(InputError, match="screen_chi2"):
        LearnParams(screen_chi2=0)


@pytest.fixture(scope="module")
def small_set():
    """14 exposures, 512 px, strong distortion, true outline centres + 0.05 px noise, and start values."""
    from fluorocal.stages.adjust import Orientation
    from fluorocal.stages.artifacts import Observations
    from fluorocal.stages.geometry import quat_multiply, quat_normalize, rotvec_to_quat
    from fluorocal.stages.simulate import SimulateParams, simulate

    size = 512
    params = SimulateParams(n_frames=14, image_size_px=size, distortion="strong", seed=4)
    data = simulate(params, render=False)
    frames = data.truth.frames[0]
    keep = [~(f.overlap | f.field_edge) for f in frames]
    rng = np.random.default_rng(11)
    xy = np.concatenate([f.outline_xy_px[k] for f, k in zip(frames, keep)])
    xy = xy + rng.normal(0, NOISE_PX, xy.shape)
    exposure = np.concatenate([np.full(k.sum(), f.exposure) for f, k in zip(frames, keep)])
    ids = np.concatenate([f.ids[k] for f, k in zip(frames, keep)])
    acq = data.truth.acquisition
    n = params.n_frames
    q = quat_normalize(quat_multiply(np.array([rotvec_to_quat(v) for v in rng.normal(0, 0.01, (n, 3))]), acq.q[0]))
    iop = [[(size - 1) / 2, (size - 1) / 2, acq.systems[0].iop_px[2] * 1.01]]
    initial = Orientation(iop, np.arange(n), q, acq.source_mm[0] + rng.normal(0, 3, (n, 3)))
    rows, moved = _gross(rng, len(xy))

    def observations(points):
        return Observations(
            np.zeros(len(points)), exposure, ids, points, np.tile([NOISE_PX, NOISE_PX, 0.0], (len(points), 1))
        )

    bad = xy.copy()
    bad[rows] += moved
    return observations(xy), observations(bad), rows, data.phantom, initial, size, params.fov_radius_px


def test_gross_errors_leave_the_learned_field_as_on_clean_data(small_set):
    clean_obs, bad_obs, rows, phantom, initial, size, fov_radius_px = small_set
    runs = [calibrate(o, phantom, initial, image_size=(size, size), params=LearnParams()) for o in (clean_obs, bad_obs)]
    clean, bad = (r.fields[0] for r in runs)
    g = np.linspace(0, size - 1, 48)
    pts = np.column_stack([a.ravel() for a in np.meshgrid(g, g)])
    c = (size - 1) / 2
    pts = pts[
        (np.hypot(pts[:, 0] - c, pts[:, 1] - c) < 0.8 * fov_radius_px) & clean.support_at(pts) & bad.support_at(pts)
    ]
    a, b = pts - bad.correction_at(pts), pts - clean.correction_at(pts)
    H, _ = cv2.findHomography(a, b, 0)
    diff = np.linalg.norm(cv2.perspectiveTransform(a[None], H)[0] - b, axis=1)
    # modulo a homography: 14 exposures fix the principal point only to ~3 px (its std), and the loop's
    # path through that weak direction differs between the runs. Measured 0.0080 px (earlier 0.018 px;
    # seed 3: 0.031 px); before the loop was made robust 0.17 px (0.29 px). What is left is the clean field's
    # own noise (node sigma ~0.1 px) seen through the 5 % of observations dropped with the gross errors
    # (0.1 x sqrt(0.05) ~ 0.02 px) and the loop's different path; bound 1.9x the measured.
    assert np.sqrt(np.mean(diff**2)) < 0.015
    res, adj = runs[1], runs[1].adjustment
    contaminated = np.zeros(len(bad_obs), bool)
    contaminated[rows] = True
    # no gross error the final adjustment flags was learned from (the few it accepts sit on beads
    # with too few observations to tell: measured 0 of 157, earlier 3)
    assert not np.any(res.trained & ~adj.inlier & contaminated)
    assert np.sum(res.trained & contaminated) <= 0.02 * len(rows)


def test_local_screen_from_the_pool_neighbour_table_equals_its_own_kd_tree():
    """The kNN's table of a system's observations gives the screen of a subset its own nearest neighbours.

    The same neighbours as the screen's KD-tree (distinct random points: no ties), hence the same screen.
    """
    from fluorocal.stages.learn.knn import pool_neighbours

    rng = np.random.default_rng(21)
    pool = rng.uniform(0, 200, (3000, 2))
    r = 0.01 * pool + rng.normal(0, 0.05, pool.shape)
    r[:30] += 2.0
    var = np.full(pool.shape, 0.05**2)
    cache = {}
    assert pool_neighbours(cache, pool, 16) is None  # no table yet
    cross_validate_k(pool, r, var, k_grid=(4, 16), n_folds=10, seed=0, neighbour_cache=cache, neighbour_pool_px=pool)
    sel = np.sort(rng.choice(len(pool), 2800, replace=False))
    near = pool_neighbours(cache, pool[sel], 16)
    _, expected = KDTree(pool[sel]).query(pool[sel], k=17)
    np.testing.assert_array_equal(near, expected[:, 1:])
    plain = local_screen(pool[sel], r[sel], var[sel], chi2=23.0)
    cached = local_screen(pool[sel], r[sel], var[sel], chi2=23.0, neighbours=near)
    np.testing.assert_array_equal(cached.keep, plain.keep)
    assert cached.cost_cap == plain.cost_cap
    assert pool_neighbours(cache, pool[sel] + 0.5, 16) is None  # points not in the table


def test_pool_neighbours_of_a_subset_thinned_in_one_half_equal_a_kd_tree(monkeypatch):
    """A subset with most of some points' table neighbours left out: the same neighbours as its own KD-tree.

    Such points' neighbours are looked for further along their table row, then by a KD-tree.
    Left of x = 100 one point in three is kept (a row's first 2 m + 8 entries hold about 13 of the 17 needed, its
    whole row of about 90 more than enough), left of x = 20 one in fifteen (a whole row falls short too).
    """
    from fluorocal.stages.learn import knn
    from fluorocal.stages.learn.knn import pool_neighbours

    rng = np.random.default_rng(5)
    pool = rng.uniform(0, 200, (3000, 2))
    r = rng.normal(0, 0.05, pool.shape)
    cache = {}
    cross_validate_k(
        pool,
        r,
        np.full(pool.shape, 0.05**2),
        k_grid=(4, 64),
        n_folds=10,
        seed=0,
        neighbour_cache=cache,
        neighbour_pool_px=pool,
    )
    i = np.arange(len(pool))
    keep = (pool[:, 0] > 100) | ((pool[:, 0] > 20) & (i % 3 == 0)) | (i % 15 == 0)
    sel = np.flatnonzero(keep)
    asked = []

    class CountingKDTree(KDTree):
        def query(self, x, k=1, **kwargs):
            if k > 1:  # k = 1: the table's lookup of the subset's rows
                asked.append(len(x))
            return super().query(x, k=k, **kwargs)

    monkeypatch.setattr(knn, "KDTree", CountingKDTree)
    near = pool_neighbours(cache, pool[sel], 16)
    _, expected = KDTree(pool[sel]).query(pool[sel], k=17)
    np.testing.assert_array_equal(near, expected[:, 1:])
    # only the points whose whole row falls short (left of x = 20, about one in a hundred) go to a KD-tree
    assert 0 < sum(asked) < 0.02 * len(sel)


def test_gridded_knn_from_the_node_table_equals_its_own_kd_tree():
    """Subsets of a pool, their grid nodes' neighbours and support counts read from the cache's node table.

    The same field, uncertainty and support as the nodes' neighbours from the subset's own KD-tree give, bit for
    bit (distinct random points: no ties). Left of x = 40 one point in twenty is kept: nodes there fall short of
    neighbours in their table rows (queried instead); right of it the rows end inside the support radius at some
    nodes (counted by the KD-tree instead) and reach beyond it at others (the table's count). The second subset
    (fewer points, refitted with the first's k) reuses the node table.
    """
    from fluorocal.stages.learn.knn import fit_knn_field
    from fluorocal.stages.learn.nodes import GridSpec

    rng = np.random.default_rng(8)
    pool = rng.uniform(0, 200, (3000, 2))
    r = 0.01 * pool + rng.normal(0, 0.05, pool.shape)
    var = np.full(pool.shape, 0.05**2)
    grid = GridSpec(spacing_px=8.0, support_radius_px=16.0, min_support=3)
    cache, i, tables, cv = {}, np.arange(len(pool)), [], None
    for step in (3, 4):
        sel = np.flatnonzero(((pool[:, 0] > 40) & (i % step != 0)) | (i % 20 == 0))
        args = (pool[sel], r[sel], var[sel])
        options = dict(image_size=(200, 200), grid=grid, neighbour_cache=cache, neighbour_pool_px=pool, cv=cv)
        cached, cv = fit_knn_field(*args, **options)
        fresh, _ = fit_knn_field(*args, image_size=(200, 200), grid=grid, cv=cv)
        tables.append(cache["nodes"])
        for name in ("delta_px", "sigma_px", "support"):
            np.testing.assert_array_equal(getattr(cached, name), getattr(fresh, name))
        dist = tables[-1].dist[:, -1]
        assert np.any(dist <= grid.support_radius_px) and np.any(dist > grid.support_radius_px)
        assert 0 < np.sum(~fresh.support) < fresh.support.size
    assert tables[1] is tables[0]


def _gridded_pair(pool, sel, grid, cache, cv=None):
    """A subset's field from the cache's node table and from its own KD-tree (the refit's ``cv`` when given)."""
    from fluorocal.stages.learn.knn import fit_knn_field

    rng = np.random.default_rng(3)
    r = 0.01 * pool + rng.normal(0, 0.05, pool.shape)
    args, var = (pool[sel], r[sel]), np.full((len(sel), 2), 0.05**2)
    cached, cv = fit_knn_field(
        *args, var, image_size=(200, 200), grid=grid, neighbour_cache=cache, neighbour_pool_px=pool, cv=cv
    )
    fresh, _ = fit_knn_field(*args, var, image_size=(200, 200), grid=grid, cv=cv)
    return cached, fresh, cv


def test_gridded_knn_from_the_node_table_with_ties_equals_its_own_kd_tree():
    """Points on a 4 px lattice, each observed twice (duplicate positions), and grid nodes between them.

    Many nodes have neighbours at one distance; the KD-tree orders such ties its own way (not by row, and not
    alike for different k), so the node table leaves those nodes to it: the same field as the subset's own tree.
    """
    from fluorocal.stages.learn.nodes import GridSpec

    g = np.arange(0.0, 200.0, 4.0)
    lattice = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    pool = np.vstack([lattice, lattice])
    i = np.arange(len(pool))
    sel = np.flatnonzero((i % 3 != 0) & (i < len(lattice)) | (i % 7 == 0))
    cache, grid, cv = {}, GridSpec(spacing_px=8.0, support_radius_px=16.0, min_support=3), None
    for _ in range(2):  # the cross-validation's subset, then a few less refitted with its k
        cached, fresh, cv = _gridded_pair(pool, sel, grid, cache, cv)
        assert cache["nodes"] is not None and cache["nodes"].tied.any()
        for name in ("delta_px", "sigma_px", "support"):
            np.testing.assert_array_equal(getattr(cached, name), getattr(fresh, name))
        sel = sel[sel % 11 != 0]


def test_node_table_support_counts_a_point_at_the_radius_as_the_kd_tree_does():
    """A point whose distance from a node rounds to the support radius, its square just above the radius's.

    The KD-tree's ball leaves it out; the table's count must too: that node has two points within the radius,
    one short of the support it needs (ground truth: the squared distance exceeds the squared radius).
    """
    from fluorocal.stages.learn.nodes import GridSpec

    grid = GridSpec(spacing_px=8.0, support_radius_px=16.0, min_support=3)
    node, radius = np.array([47.5, 47.5]), grid.support_radius_px
    edge = next(
        e
        for e in node + [radius, 0] + np.outer(np.linspace(1e-8, 1e-6, 5000), [0, 1])
        if _rounds_onto(e - node, radius)
    )
    assert KDTree([edge]).query(node)[0] == radius  # the case: the tree's distance is the radius
    rng = np.random.default_rng(2)
    dense = rng.uniform([100, 0], [200, 200], (1500, 2))
    pool = np.vstack([dense, node + [[3.0, 4.0], [-5.0, 2.0]], [edge]])
    cached, fresh, _ = _gridded_pair(pool, np.arange(len(pool)), grid, {})
    at = (np.abs(cached.x_nodes_px - node[0]) < 1e-9)[None, :] & (np.abs(cached.y_nodes_px - node[1]) < 1e-9)[:, None]
    assert not fresh.support[at].item()
    np.testing.assert_array_equal(cached.support, fresh.support)


def _rounds_onto(d, radius):
    """Whether the offset ``d``'s length rounds to ``radius`` while its square exceeds the radius's."""
    return d @ d > radius**2 and np.sqrt(d @ d) == radius


def test_node_table_follows_its_cache_to_a_new_grid_and_a_set_not_from_the_pool():
    """One cache through a pool's subset, the same subset on a coarser grid, then points not in the pool.

    Each field equals the one from the set's own KD-tree: the node table is rebuilt for new nodes, and dropped
    with the neighbour table it indexes (rebuilt from the set itself when the set is not drawn from the pool).
    """
    from fluorocal.stages.learn.nodes import GridSpec

    rng = np.random.default_rng(4)
    pool = rng.uniform(0, 200, (2000, 2))
    sel, cache = np.flatnonzero(np.arange(len(pool)) % 4 != 0), {}
    for grid, points in ((8.0, pool), (12.0, pool), (12.0, pool + 0.25)):
        cached, fresh, _ = _gridded_pair(points, sel, GridSpec(spacing_px=grid, support_radius_px=16.0), cache)
        assert cache["nodes"] is not None
        for name in ("delta_px", "sigma_px", "support"):
            np.testing.assert_array_equal(getattr(cached, name), getattr(fresh, name))
