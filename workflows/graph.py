"""Expansion of a workflow into a graph of stage tasks.

Every variant (study x sweep point) of a :class:`~mavispm.workflows.config.Workflow`
becomes the chain::

    cluster ---------------------------+--> frames[scene, epoch] --> stars[scene, epoch]
    (or an external catalogue file)    |                                   |
    optics[scene] (PSF grid) ----------+         propermotions[scene] <----+ (all epochs)
    calibration[scene] (mask, optional) +

(in observer mode, ``[measure] later_epochs = "measured"``, the default, the
stars node of each later epoch also takes the earlier epochs' stars nodes as
its ``earlier`` input: it starts from their measured positions)
                                                          |
                                                 dynamics[scene]

Node identifiers are readable paths (``imbh/frames/III/e1``) that also name the
products in the run directory. Seeds are derived from the workflow seed and the
node's stage, scene and epoch only (never from the study or the execution
order), so IMBH and no-IMBH studies share their random streams and a product
is the same whatever the executor runs first.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

from mavispm.workflows.config import Variant, Workflow

__all__ = [
    "Node",
    "catalogue_ref",
    "derive_seed",
    "expand",
    "has_imbh",
    "topological",
]


@dataclass(frozen=True)
class Node:
    """One stage task.

    Parameters
    ----------
    id : str
        Readable path, unique in the run.
    stage : str
        Stage name in the registry.
    settings : dict
        The stage's settings table.
    params : dict
        Node parameters passed to the stage adapter (epoch, scene, switches).
    seed : int or None
    inputs : dict
        Input name to upstream node id, or list of node ids.
    external : dict
        Input name to an external file path (hashed by content).
    labels : dict
        ``study``, ``point``, ``scene``, ``epoch`` (for reports).
    sweep : dict
        Swept values of the node's variant.
    """

    id: str
    stage: str
    settings: dict
    params: dict
    seed: int | None
    inputs: dict = field(default_factory=dict)
    external: dict = field(default_factory=dict)
    labels: dict = field(default_factory=dict)
    sweep: dict = field(default_factory=dict)

    def upstream(self) -> list[str]:
        """Ids of the nodes this node reads."""
        out: list[str] = []
        for ref in self.inputs.values():
            out.extend(ref if isinstance(ref, list) else [ref])
        return out


def derive_seed(base: int, *parts: str) -> int:
    """A reproducible 31-bit seed from the workflow seed and a node's path parts.

    Parameters
    ----------
    base : int
        The workflow seed.
    *parts : str
        The node's path parts (study, point, scene, epoch, stage, ...).

    Returns
    -------
    int
        A seed in [0, 2**31), from the SHA-256 of the joined text.
    """
    text = "|".join([str(int(base)), *map(str, parts)])
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:4], "big") & 0x7FFFFFFF


def expand(workflow: Workflow) -> dict[str, Node]:
    """All nodes of the workflow in a topological order (inputs before users).

    Parameters
    ----------
    workflow : Workflow
        The validated workflow.

    Returns
    -------
    dict of str to Node
        Node id to node; insertion order is a valid execution order.
    """
    nodes: dict[str, Node] = {}
    for variant in workflow.variants:
        truths = _truth_catalogues(variant, workflow.variants)
        for node in _variant_nodes(variant, workflow, truths):
            nodes[node.id] = node
    return topological(nodes)


def topological(nodes: dict[str, Node]) -> dict[str, Node]:
    """The nodes reordered so every node follows its inputs (stable otherwise).

    Parameters
    ----------
    nodes : dict of str to Node
        Node id to node.

    Returns
    -------
    dict of str to Node
        The same nodes, inputs first.

    Raises
    ------
    ValueError
        On a dependency cycle or an input that is not a node.
    """
    out: dict[str, Node] = {}
    visiting: set[str] = set()

    def visit(nid: str) -> None:
        if nid in out:
            return
        if nid in visiting or nid not in nodes:
            raise ValueError(f"bad stage graph at node '{nid}' (cycle or missing input)")
        visiting.add(nid)
        for up in nodes[nid].upstream():
            visit(up)
        visiting.discard(nid)
        out[nid] = nodes[nid]

    for nid in nodes:
        visit(nid)
    return out


def catalogue_ref(v: Variant) -> tuple[str, str]:
    """Where a variant's catalogue comes from.

    Parameters
    ----------
    v : Variant
        The variant.

    Returns
    -------
    tuple of str
        ``("node", id)`` of its cluster node, or ``("file", path)`` of its external catalogue.
    """
    if v.cluster is not None:
        return "node", "/".join(p for p in (v.label, "cluster") if p)
    return "file", str(v.catalogue)


def has_imbh(v: Variant) -> bool | None:
    """Whether a variant's generated cluster has an IMBH.

    Parameters
    ----------
    v : Variant
        The variant.

    Returns
    -------
    bool or None
        True when its ``imbh_mass`` is > 0 [solMass]; None for an external catalogue.
    """
    if v.cluster is None:
        return None
    import astropy.units as u

    return float(u.Quantity(v.cluster.get("imbh_mass", 0.0), u.solMass).value) > 0


def _truth_catalogues(v: Variant, variants) -> dict[str, tuple[str, str]]:
    """Truth catalogues of the dynamics comparison: IMBH and no-IMBH studies of the same point.

    The variant's own catalogue fills the slot it belongs to; a sibling study
    (same sweep point) fills the other, so each fit's plots show both truths.
    """
    siblings = [w for w in variants if w.point.label == v.point.label]
    out = {}
    for slot, want in (("truth", True), ("truth_no_imbh", False)):
        for w in sorted(siblings, key=lambda w: w is not v):  # the variant itself first
            if has_imbh(w) is want:
                out[slot] = catalogue_ref(w)
                break
    return out


def _variant_nodes(v: Variant, workflow: Workflow, truths: dict) -> list[Node]:
    prefix = v.label
    base_labels = {"study": v.study, "point": v.point.label}
    sweep = dict(v.point.values)

    def nid(*parts: str) -> str:
        return "/".join(p for p in (prefix, *parts) if p)

    def make(stage, parts, settings, params, seed, inputs=None, external=None, **labels):
        return Node(
            id=nid(*parts),
            stage=stage,
            settings=dict(settings),
            params=params,
            seed=seed,
            inputs=inputs or {},
            external=external or {},
            labels={**base_labels, **labels},
            sweep=sweep,
        )

    out: list[Node] = []
    epochs = [[e.name, e.time] for e in v.epochs]
    cat_inputs, cat_external = {}, {}
    if v.cluster is not None:
        star_list = (v.cluster.get("external") or {}).get("path")
        cluster = make(
            "cluster",
            ["cluster"],
            v.cluster,
            {"epochs": epochs},
            derive_seed(v.seed, "cluster"),
            external={"star_list": star_list} if star_list else None,
        )
        out.append(cluster)
        cat_inputs["catalogue"] = cluster.id
    else:
        cat_external["catalogue"] = str(v.catalogue)
    outputs = workflow.outputs
    for scene in v.scenes:
        psf_inputs = {}
        if scene.optics is not None:  # the scene's optics: a PSF grid node of its own
            optics = make(
                "optics",
                ["optics", scene.name],
                scene.optics,
                {"plots": outputs.plots},
                None,
                scene=scene.name,
            )
            out.append(optics)
            psf_inputs["psf"] = optics.id
        if scene.calibration is not None:  # the calibration mask through this distortion
            calibration = make(
                "calibration",
                ["calibration", scene.name],
                scene.calibration,
                {
                    "distortion": dict((scene.optics or {}).get("distortion") or {}),
                    **(
                        {"scene": scene.scene}
                        if scene.calibration.get("imaging") == "rendered"
                        else {}
                    ),
                },
                derive_seed(v.seed, "calibration", scene.name),
                scene=scene.name,
            )
            out.append(calibration)
            psf_inputs["calibration"] = calibration.id
        measured = []
        # observer mode (the default): a later epoch starts from the earlier epochs'
        # measured positions, so its stars node depends on theirs
        observer = scene.measure is not None and (
            scene.measure.get("later_epochs", "measured") == "measured"
        )
        for epoch in sorted(v.epochs, key=lambda e: e.time):
            frames = make(
                "frames",
                ["frames", scene.name, epoch.name],
                scene.scene,
                {
                    "epoch": epoch.name,
                    "epoch_time": epoch.time,
                    "scene": scene.name,
                    "fits": outputs.fits,
                },
                derive_seed(v.seed, "frames", scene.name, epoch.name),
                inputs={**cat_inputs, **psf_inputs},
                external=cat_external,
                scene=scene.name,
                epoch=epoch.name,
            )
            out.append(frames)
            if scene.measure is None:
                continue
            stars = make(
                "stars",
                ["stars", scene.name, epoch.name],
                scene.measure,
                {"epoch": epoch.name},
                derive_seed(v.seed, "stars", scene.name, epoch.name),
                inputs={
                    "frames": frames.id,
                    **({"earlier": list(measured)} if observer and measured else {}),
                    # the scene's PSF grid: the PSF-R prior of the measurement
                    **({"psf_prior": psf_inputs["psf"]} if "psf" in psf_inputs else {}),
                },
                scene=scene.name,
                epoch=epoch.name,
            )
            out.append(stars)
            measured.append(stars.id)
        if v.propermotions is None:
            continue
        truth_in = {"truth": cat_inputs["catalogue"]} if cat_inputs else {}
        truth_ext = {"truth": cat_external["catalogue"]} if cat_external else {}
        pm = make(
            "propermotions",
            ["propermotions", scene.name],
            v.propermotions,
            {"epochs": epochs},
            None,
            inputs={"measured": measured, **truth_in},
            external=truth_ext,
            scene=scene.name,
        )
        out.append(pm)
        if v.dynamics is None:
            continue
        refs = dict(truths)
        if v.dynamics.get("completeness_source") == "artificial_stars":
            # in a simulation the variant's own catalogue is the artificial-star test
            refs["artificial_stars"] = catalogue_ref(v)
        out.append(
            make(
                "dynamics",
                ["dynamics", scene.name],
                v.dynamics,
                {"plots": outputs.plots},
                derive_seed(v.seed, "dynamics", scene.name),
                inputs={
                    "propermotions": pm.id,
                    **{k: ref for k, (kind, ref) in refs.items() if kind == "node"},
                },
                external={k: ref for k, (kind, ref) in refs.items() if kind == "file"},
                scene=scene.name,
            )
        )
    return out
