"""Expansion of a workflow into a graph of stage tasks.

Every variant (study x sweep point) of a :class:`~mavispm.workflows.config.Workflow`
becomes the chain::

    cluster ---------------------------+--> frames[scene, epoch] --> stars[scene, epoch]
    (or an external catalogue file)    |                                   |
    optics[scene] (PSF grid) ----------+         propermotions[scene] <----+ (all epochs)
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


@dataclass(frozen=True)
class Node:
    """One stage task.

    Attributes
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
    """A reproducible 31-bit seed from the workflow seed and a node's path parts."""
    text = "|".join([str(int(base)), *map(str, parts)])
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:4], "big") & 0x7FFFFFFF


def expand(workflow: Workflow) -> dict[str, Node]:
    """All nodes of the workflow in a topological order (inputs before users).

    Returns
    -------
    dict of str to Node
        Node id to node; insertion order is a valid execution order.
    """
    nodes: dict[str, Node] = {}
    for variant in workflow.variants:
        for node in _variant_nodes(variant, workflow):
            nodes[node.id] = node
    return nodes


def _variant_nodes(v: Variant, workflow: Workflow) -> list[Node]:
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
        measured = []
        for epoch in v.epochs:
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
                inputs={"frames": frames.id},
                scene=scene.name,
                epoch=epoch.name,
            )
            out.append(stars)
            measured.append(stars.id)
        if v.propermotions is None:
            continue
        pm = make(
            "propermotions",
            ["propermotions", scene.name],
            v.propermotions,
            {"epochs": epochs},
            None,
            inputs={"measured": measured},
            scene=scene.name,
        )
        out.append(pm)
        if v.dynamics is None:
            continue
        out.append(
            make(
                "dynamics",
                ["dynamics", scene.name],
                v.dynamics,
                {"plots": outputs.plots},
                derive_seed(v.seed, "dynamics", scene.name),
                inputs={"propermotions": pm.id},
                scene=scene.name,
            )
        )
    return out
