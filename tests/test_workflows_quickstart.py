"""The shipped quickstart workflow, end to end through the real stages."""

from __future__ import annotations

import astropy.units as u
import numpy as np
import pytest
from workflows_helpers import ALL_NODES

from mavispm.core.catalogue import read_catalogue
from mavispm.core.products import read_product
from mavispm.workflows.config import load_workflow, shipped_workflows
from mavispm.workflows.runner import run_workflow

#: Lighter sampler settings than the shipped file (the test checks the chain, not the
#: posterior; the quickstart's posterior is the nested-sampling run's); everything else
#: is the quickstart as users run it.
FAST = {"dynamics.nlive": 25}


def test_all_shipped_workflows_are_valid():
    names = shipped_workflows()
    assert {
        "quickstart.toml",
        "astrometric_budget.toml",
        "ngc3201_imbh.toml",
        "pm_accuracy.toml",
        "imbh_detectability.toml",
    } <= set(names)
    budget = load_workflow("astrometric_budget")
    assert [s.name for s in budget.variants[0].scenes] == [
        "I",
        "Ia",
        "Ib",
        "II",
        "III",
        "IV",
        "IIIx3",
        "IVx3",
    ]
    imbh = load_workflow("ngc3201_imbh")
    assert sorted(v.study for v in imbh.variants) == ["imbh", "no_imbh"]
    assert [e.time for e in imbh.variants[0].epochs] == [0.0, 10.0]
    assert len(load_workflow("pm_accuracy").variants) == 4
    detect = load_workflow("imbh_detectability")
    masses = sorted({v.point.values["mass"] for v in detect.variants})
    assert masses == [0, 500, 1000, 1500, 3000]  # mass 0: the no-IMBH reference
    # null cases: a black-hole subsystem and radial anisotropy, each at every mass
    assert {v.study for v in detect.variants} == {"reference", "bh_subsystem", "radial_anisotropy"}
    assert len(detect.variants) == 15


def test_imbh_workflows_measure_completeness_from_their_own_catalogue():
    """The IMBH workflows' dynamics nodes get their own variant's catalogue as the
    artificial-star test (``completeness_source = "artificial_stars"``); a workflow without
    it gets no such input (its cache keys do not change)."""
    from mavispm.workflows.graph import expand

    for name in ("ngc3201_imbh", "imbh_detectability"):
        nodes = expand(load_workflow(name))
        dyn = [n for n in nodes.values() if n.stage == "dynamics"]
        assert dyn
        for node in dyn:
            own = node.id.split("/dynamics/")[0] + "/cluster"
            assert node.inputs["artificial_stars"] == own, node.id
            assert node.inputs["propermotions"].startswith(node.id.split("/dynamics/")[0])
    quick = expand(load_workflow("quickstart"))
    assert all("artificial_stars" not in n.inputs for n in quick.values())


def test_quickstart_end_to_end(tmp_path):
    wf = load_workflow("quickstart", overrides=FAST)  # found by name among the shipped files
    result = run_workflow(wf, workdir=tmp_path, progress=False)
    assert set(result.ran) == ALL_NODES

    cat = read_catalogue(result.product("cluster"))
    assert list(cat.epochs) == ["e0", "e1"]
    frames = read_product(result.product("frames/main/e1"), "frames")
    assert frames.arrays["image"].shape == (600, 600)
    assert result.product("frames/main/e1", "fits").is_file()

    # measured positions against the rendered truth: bright stars to well under a pixel
    stars = read_product(result.product("stars/main/e0"), "measured").tables["stars"]
    ok = (np.asarray(stars["flag"]) & (1 | 16 | 32)) == 0
    bright = ok & (stars["mag"].to_value(u.mag) < 21)
    dx = (stars["x"] - stars["x_true"]).to_value(u.mas)[bright]
    assert bright.sum() > 20
    assert np.median(np.abs(dx)) < 1.0  # mas: well under a pixel (7.5 mas); see docs/measure.md

    # proper motions against the catalogue's true motions (matched by id)
    pms = read_product(result.product("propermotions/main"), "propermotions").tables["stars"]
    truth = cat.epochs["e0"]
    index = {int(i): k for k, i in enumerate(truth["id"])}
    rows = [index[int(i)] for i in pms["id"]]
    true_pm_x = truth["pm_x"].to_value(u.mas / u.yr)[rows]
    pm_x = pms["pm_x"].to_value(u.mas / u.yr)
    good = np.isfinite(pm_x) & (pms["mag"].to_value(u.mag) < 22)
    assert good.sum() > 20
    resid = pm_x[good] - true_pm_x[good]
    resid -= np.median(resid)  # PMs are relative to the cluster's mean motion
    assert np.median(np.abs(resid)) < 0.05  # mas/yr: the paper's 50 microarcsec goal
    assert np.corrcoef(pm_x[good], true_pm_x[good])[0, 1] > 0.95

    fit = read_product(result.product("dynamics/main"), "dynamics").attrs
    assert np.isfinite(fit["ln_bayes_factor"])
    report = (result.rundir / "report.md").read_text()
    assert "Proper-motion accuracy" in report and "IMBH model comparison" in report
    # the injected IMBH mass, read from the rendered truth catalogue, stands beside the fit
    injected = u.Quantity(cat.attrs["imbh_mass"], u.solMass).to_value(u.solMass)
    assert injected > 0
    row = next(r for r in report.splitlines() if r.startswith("| imbh_mass_injected (truth) |"))
    assert float(row.split("|")[2]) == pytest.approx(injected, rel=1e-3)

    again = run_workflow(wf, workdir=tmp_path, progress=False)
    assert again.ran == []


#: Attributes that record input file paths (different work directories); every dataset
#: and every other attribute except the timings (``time_*``) must be bitwise identical.
PATH_ATTRS = ("frames", "inputs", "propermotions", "config")


@pytest.mark.slow
def test_quickstart_products_identical_on_dask_and_threads(tmp_path):
    """Real stages: a LocalCluster on loopback gives the in-process products bit for bit."""
    import distributed
    from workflows_helpers import fingerprints

    wf = load_workflow("quickstart", overrides=FAST)
    local = run_workflow(wf, workdir=tmp_path / "threads", scheduler="threads", progress=False)
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None
    ) as cluster:
        remote = run_workflow(
            wf, workdir=tmp_path / "dask", scheduler=cluster.scheduler_address, progress=False
        )
    a = fingerprints(local.rundir, PATH_ATTRS)
    assert len(a) >= 8
    assert a == fingerprints(remote.rundir, PATH_ATTRS)


@pytest.mark.slow
def test_quickstart_dynamics_holds_the_injected_imbh_on_true_motions(tmp_path):
    """The quickstart's own ``[dynamics]`` table fitted to the true motions of three
    catalogues of its own ``[cluster]`` table (seeds 1-3): the 95% interval of M_BH
    holds the catalogue's injected mass every time. The cored quick look used before
    2026-12-03 missed it in all three (upper 95% bounds 1290-1411 for 1500)."""
    from mavispm.dynamics.cli import run_stage as fit_dynamics
    from mavispm.simulate.cluster.cli import run_stage as simulate_cluster

    variant = load_workflow("quickstart").variants[0]
    cluster = {**variant.cluster, "epochs": [e.time for e in variant.epochs]}
    dynamics = dict(variant.dynamics)
    ratios = []
    for seed in (1, 2, 3):
        cat = simulate_cluster(cluster, tmp_path / f"c{seed}.h5", seed)
        truth = u.Quantity(read_catalogue(cat).attrs["imbh_mass"], u.solMass).to_value(u.solMass)
        out = fit_dynamics(None, dynamics, tmp_path / f"d{seed}.h5", 1, from_catalogue=cat)
        attrs = read_product(out, "dynamics").attrs
        lo, hi = (attrs[f"bh_mass_{k}"].to_value(u.solMass) for k in ("lo95", "hi95"))
        assert lo <= truth <= hi, (seed, lo, hi, truth)
        ratios.append(attrs["bh_mass_median"].to_value(u.solMass) / truth)
    assert np.mean(ratios) > 0.75, ratios  # the cored quick look: 0.64 on average


@pytest.mark.slow
def test_quickstart_dynamics_law_unbiased_with_many_stars(tmp_path):
    """With 100x the quickstart's stars (30,000 true motions inside the same 2.5", the
    same cluster model) the maximum of the quickstart's ``imbh`` posterior lies within 7%
    of the catalogue's injected M_BH. The line-of-sight mixture of Gaussian 3-D
    velocities (the stage's default law, the quickstart's until 2026-12-03) put it at
    0.85-0.87 of the truth on three such catalogues: the generator's velocities, drawn
    from its distribution function, are not Gaussian near the IMBH."""
    from mavispm.dynamics.cli import load_catalogue_stars, validate_settings
    from mavispm.dynamics.fit import make_likelihood, parameter_space
    from mavispm.dynamics.sampling import find_map
    from mavispm.simulate.cluster.cli import run_stage as simulate_cluster

    variant = load_workflow("quickstart").variants[0]
    cluster = {**variant.cluster, "epochs": [e.time for e in variant.epochs], "n_stars": 30000}
    cat = simulate_cluster(cluster, tmp_path / "c.h5", 101)
    truth = u.Quantity(read_catalogue(cat).attrs["imbh_mass"], u.solMass).to_value(u.solMass)
    settings = validate_settings(dict(variant.dynamics))
    stars, distance = load_catalogue_stars(cat, settings)
    assert len(stars.R) > 25000
    space = parameter_space(settings, distance, "imbh")
    like = make_likelihood(stars, space, settings, distance)
    best = space.from_scaled(find_map(like, space))
    bh = best[space.names.index("bh_mass")]
    assert bh / truth == pytest.approx(1.0, abs=0.07), (bh, truth, dict(zip(space.names, best)))


@pytest.mark.slow
@pytest.mark.parametrize("profile", ["constant", "radial"])
def test_quickstart_free_kurtosis_law_unbiased_and_platykurtic(tmp_path, profile):
    """The free-kurtosis law on the 30,000-star catalogue of the test above: the maximum of
    the ``imbh`` posterior lies within 7% of the injected M_BH (0.97-1.03 on three such
    catalogues, docs/dynamics.md) and the fitted shape is flatter than a Gaussian where
    the catalogue's own true motions are: kappa (or kappa_outer) < 0 wherever the sample
    kurtosis of the motions outside the inner anchor, each component scaled by its
    equal-count-bin dispersion, is below 3."""
    from mavispm.dynamics.cli import load_catalogue_stars, validate_settings
    from mavispm.dynamics.fit import make_likelihood, parameter_space
    from mavispm.dynamics.sampling import find_map
    from mavispm.simulate.cluster.cli import run_stage as simulate_cluster

    variant = load_workflow("quickstart").variants[0]
    cluster = {**variant.cluster, "epochs": [e.time for e in variant.epochs], "n_stars": 30000}
    cat = simulate_cluster(cluster, tmp_path / "c.h5", 101)
    truth = u.Quantity(read_catalogue(cat).attrs["imbh_mass"], u.solMass).to_value(u.solMass)
    dyn = {**variant.dynamics, "velocity_law": "free_kurtosis", "kappa_profile": profile}
    settings = validate_settings(dyn)
    stars, distance = load_catalogue_stars(cat, settings)
    # the data's own shape: motions outside the inner anchor, scaled per 2,000-star bin
    order = np.argsort(stars.R)
    outer = order[int(0.1 * order.size) :]
    scaled = []
    for chunk in np.array_split(outer, outer.size // 2000):
        for v in (stars.v_r[chunk], stars.v_t[chunk]):
            scaled.append(v / np.sqrt(np.mean(v * v)))
    scaled = np.concatenate(scaled)
    assert np.mean(scaled**4) < 3.0
    space = parameter_space(settings, distance, "imbh")
    like = make_likelihood(stars, space, settings, distance)
    best = dict(zip(space.names, space.from_scaled(find_map(like, space))))
    assert best["bh_mass"] / truth == pytest.approx(1.0, abs=0.07), (best, truth)
    assert best["kappa" if profile == "constant" else "kappa_outer"] < 0, best
