"""Export of the trained inference chain to ONNX (fp32), dynamic int8 quantisation, and the bundle.

The chain is written node by node with ``onnx.helper`` from the trained weights: plane encoder
(2 graph convs + FC) -> generator (5 FC, BatchNorm folded into the weights) -> object decoder
(FC, concat with the target normals, 2 graph convs) -> colour GAE (2 graph convs + L.n). Writing the
graph directly (rather than tracing JAX with jax2onnx) gives stable node names, which the int8 step
needs: only the FC layers are quantised (onnxruntime dynamic quantisation, int8 weights, uint8
activations); the adjacency products stay fp32 (quantising them was measured slower, and they are
where neighbour mixing happens).

ONNX interface (batch 1, one frame)::

    input   plane    float32 [1, P, 4]      preprocess_plane() output (normalised RGB, coverage)
    output  oi       float32 [1, V, 3, 3]   proxy OI / s (vertex, channel, xyz), object frame
    output  shading  float32 [1, V, 3]      proxy shading / s (multiply by s for irradiance)
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from pathlib import Path

import numpy as np

OPSET = 17
EPS_BN = 1e-5


def _fold_bn(fc: dict, bn: dict, st: dict) -> tuple[np.ndarray, np.ndarray]:
    g = np.asarray(bn["g"]) / np.sqrt(np.asarray(st["v"]) + EPS_BN)
    w = np.asarray(fc["w"]) * g[None, :]
    b = (np.asarray(fc["b"]) - np.asarray(st["m"])) * g + np.asarray(bn["b"])
    return w.astype(np.float32), b.astype(np.float32)


class _G:
    """Tiny graph builder: constants become initializers, every node gets a readable name."""

    def __init__(self):
        self.nodes, self.inits, self.n = [], [], 0
        self.fc_nodes: list[str] = []

    def const(self, name: str, arr) -> str:
        from onnx import numpy_helper

        a = np.asarray(arr)
        a = a.astype(np.int64) if a.dtype.kind in "iu" else a.astype(np.float32)
        self.inits.append(numpy_helper.from_array(a, name))
        return name

    def op(self, op: str, inputs: list[str], name: str, out: str | None = None, **attrs) -> str:
        from onnx import helper

        out = out or name + "_out"
        self.nodes.append(helper.make_node(op, inputs, [out], name=name, **attrs))
        return out

    def fc(self, x: str, w, b, name: str) -> str:
        """x @ W + b as MatMul + Add (MatMul with a constant weight: what dynamic int8 quantises)."""
        y = self.op("MatMul", [x, self.const(name + ".w", w)], name)
        self.fc_nodes.append(name)
        return self.op("Add", [y, self.const(name + ".b", b)], name + "_bias")

    def gconv(self, h: str, p: dict, a: str, name: str) -> str:
        """A_hat @ (H @ W) + b; the adjacency product stays fp32."""
        y = self.op("MatMul", [h, self.const(name + ".w", p["w"])], name + "_w")
        y = self.op("MatMul", [a, y], name + "_adj")
        return self.op("Add", [y, self.const(name + ".b", p["b"])], name + "_bias")


def build_onnx(result: dict, a_plane: np.ndarray, a_obj: np.ndarray, normals: np.ndarray, meta: dict | None = None):
    """The fp32 ONNX model (onnx.ModelProto) of the inference chain."""
    import onnx
    from onnx import TensorProto, helper

    P, V = a_plane.shape[0], a_obj.shape[0]
    g = _G()
    ap = g.const("A_plane", a_plane)
    ao = g.const("A_object", a_obj)
    nrm = g.const("normals", normals)
    pe = result["plane"]["enc"]
    x = g.op("Reshape", ["plane", g.const("shape_plane", [P, 4])], "plane_2d")
    h = g.op("Tanh", [g.gconv(x, pe["g1"], ap, "plane_enc_g1")], "plane_enc_g1_tanh")
    h = g.op("Tanh", [g.gconv(h, pe["g2"], ap, "plane_enc_g2")], "plane_enc_g2_tanh")
    h = g.op("Reshape", [h, g.const("shape_flat", [1, -1])], "plane_enc_flat")
    z = g.fc(h, pe["fc"]["w"], pe["fc"]["b"], "plane_enc_fc")
    gp, gs = result["gen"], result["gen_state"]
    for i in range(4):
        w, b = _fold_bn(gp[f"fc{i}"], gp[f"bn{i}"], gs[f"bn{i}"])
        z = g.op("LeakyRelu", [g.fc(z, w, b, f"gen_fc{i}")], f"gen_fc{i}_lrelu", alpha=0.2)
    z = g.fc(z, gp["fc4"]["w"], gp["fc4"]["b"], "gen_fc4")
    od = result["object"]["dec"]
    h = g.fc(z, od["fc"]["w"], od["fc"]["b"], "obj_dec_fc")
    h = g.op("Tanh", [g.op("Reshape", [h, g.const("shape_dec", [V, -1])], "obj_dec_vertices")], "obj_dec_tanh")
    h = g.op("Concat", [h, nrm], "obj_dec_with_normals", axis=1)
    h = g.op("Tanh", [g.gconv(h, od["g1"], ao, "obj_dec_g1")], "obj_dec_g1_tanh")
    oi9 = g.gconv(h, od["g2"], ao, "obj_dec_g2")
    oi3 = g.op("Reshape", [oi9, g.const("shape_oi3", [V, 3, 3])], "oi_v33")
    n13 = g.const("normals_v13", normals.reshape(V, 1, 3))
    e = g.op("ReduceSum", [g.op("Mul", [oi3, n13], "oi_dot_n"), g.const("axis2", [2])], "shade_ln", keepdims=0)
    c = result["colour"]
    h = g.op("Concat", [oi9, nrm, e], "colour_in", axis=1)
    h = g.op("Tanh", [g.gconv(h, c["g1"], ao, "colour_g1")], "colour_g1_tanh")
    d = g.gconv(h, c["g2"], ao, "colour_g2")
    sh = g.op("Add", [e, d], "colour_residual")
    g.op("Reshape", [oi9, g.const("shape_oi_out", [1, V, 3, 3])], "oi_out", out="oi")
    g.op("Reshape", [sh, g.const("shape_sh_out", [1, V, 3])], "shading_out", out="shading")
    graph = helper.make_graph(
        g.nodes,
        "illuminet_transfer",
        [helper.make_tensor_value_info("plane", TensorProto.FLOAT, [1, P, 4])],
        [
            helper.make_tensor_value_info("oi", TensorProto.FLOAT, [1, V, 3, 3]),
            helper.make_tensor_value_info("shading", TensorProto.FLOAT, [1, V, 3]),
        ],
        g.inits,
    )
    model = helper.make_model(
        graph,
        opset_imports=[helper.make_opsetid("", OPSET)],
        producer_name="illuminet",
        producer_version=str((meta or {}).get("version", "")),
    )
    model.ir_version = 8  # readable by onnxruntime >= 1.14
    for k, v in (meta or {}).items():
        e = model.metadata_props.add()
        e.key, e.value = str(k), str(v)
    onnx.checker.check_model(model)
    return model, g.fc_nodes


class _OrtQuantisationChatter(logging.Filter):
    """Drops onnxruntime.quantization's own warnings/infos, which it logs on the *root* logger: a
    "Please consider to run pre-processing before quantization" hint and a line per tensor without
    quantisation parameters. Errors still pass."""

    def filter(self, record: logging.LogRecord) -> bool:
        where = record.pathname.replace("\\", "/")
        return record.levelno >= logging.ERROR or "onnxruntime/quantization" not in where


def quantize_int8(fp32_path: Path, int8_path: Path, fc_nodes: list[str]) -> None:
    """Dynamic int8 quantisation of the FC MatMuls only (weights int8, activations uint8 at run time).

    onnxruntime's hints are silenced and said once here instead: its pre-processing (shape inference
    and graph optimisation) matters for static quantisation of convolutional graphs; this graph is
    already a plain MatMul/Add chain with static shapes, and only those MatMuls' weights are quantised,
    with activation scales computed at run time ("quantization parameters not specified" is expected).
    """
    from onnxruntime.quantization import QuantType, quantize_dynamic

    root = logging.getLogger()
    quiet = _OrtQuantisationChatter()
    root.addFilter(quiet)
    try:
        quantize_dynamic(
            str(fp32_path),
            str(int8_path),
            weight_type=QuantType.QInt8,
            nodes_to_quantize=list(fc_nodes),
            per_channel=False,
        )
    finally:
        root.removeFilter(quiet)
    logging.getLogger(__name__).info(
        "int8: dynamic quantisation of %d FC MatMul(s) (weights int8, activation scales at run time); "
        "onnxruntime's pre-processing hint does not apply to this graph (see quantize_int8)",
        len(fc_nodes),
    )


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def write_mesh(out: Path, geom, prior_shading: np.ndarray) -> None:
    """A bundle's ``mesh.npz``: the render mesh, the lighting proxy, the carry mapping and the
    constant-prior shading (one writer for trained and PRT-only bundles)."""
    from illuminet.runtime.assets.bundle import FILES

    np.savez_compressed(
        Path(out) / FILES["mesh"],
        vertices=geom.vertices,
        normals=geom.normals,
        faces=geom.faces,
        proxy_index=geom.proxy_index,
        proxy_edges=geom.proxy_edges,
        carry_index=geom.carry_index,
        carry_weight=geom.carry_weight,
        prior_shading=prior_shading,
    )


def write_bundle(out: str | Path, result: dict, trainer, command: str = "", extra_meta: dict | None = None) -> Path:
    """Write a bundle folder: mesh.npz, transfer_fp32.onnx, transfer_int8.onnx, bundle.json.

    ``trainer`` is the :class:`~illuminet.models.train.Trainer` (geometry, adjacency, data, config).
    Returns the bundle.json path. See docs/models.md for the format.
    """
    import onnxruntime as ort

    from illuminet import __version__
    from illuminet.models.train import predict_jax
    from illuminet.runtime.assets.bundle import BUNDLE_FORMAT, FILES
    from illuminet.runtime.stages.shading import POOL

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    g = trainer.geom
    cfg = trainer.cfg
    P, V = trainer.a_plane.shape[0], trainer.a_obj.shape[0]
    prior = trainer.data["train"]["shading"].mean(0).astype(np.float32)
    write_mesh(out, g, prior)
    model, fc_nodes = build_onnx(
        result,
        trainer.a_plane,
        trainer.a_obj,
        trainer.normals,
        {"object": cfg.object, "version": __version__, "seed": cfg.seed},
    )
    fp32 = out / FILES["fp32"]
    int8 = out / FILES["int8"]
    fp32.write_bytes(model.SerializeToString())
    quantize_int8(fp32, int8, fc_nodes)

    # check the exported chain against JAX on validation inputs
    xv = trainer.data["val"]["plane"][:16]
    _, sh_jax = predict_jax(result, trainer.a_plane, trainer.a_obj, trainer.normals, xv)
    sess = {
        k: ort.InferenceSession(str(p), providers=["CPUExecutionProvider"]) for k, p in (("fp32", fp32), ("int8", int8))
    }
    diffs = {}
    for k, s in sess.items():
        pred = np.stack([s.run(["shading"], {"plane": x[None]})[0][0] for x in xv])
        diffs[k] = float(np.abs(pred - np.asarray(sh_jax)).max())
    meta = {
        "format": BUNDLE_FORMAT,
        "name": g.name,
        "object": cfg.object,
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "package_version": __version__,
        "vertices": {
            "render": int(len(g.vertices)),
            "faces": int(len(g.faces)),
            "proxy": int(V),
            "plane_input": int(P),
        },
        "plane": {"grid": cfg.grid, "pool": POOL, "extent_m": cfg.extent_m},
        "normalisation": {
            "input": "plane irradiance / s per pooled cell (mask-weighted mean) + observed fraction; "
            "s = mean observed luminance (Rec.709 weights) of the plane irradiance",
            "output": "shading and OI are divided by s: multiply by s for scene-referred irradiance",
        },
        "onnx": {
            "input": {"plane": [1, P, 4]},
            "outputs": {"oi": [1, V, 3, 3], "shading": [1, V, 3]},
            "opset": OPSET,
            "int8_quantised_nodes": fc_nodes,
        },
        "export_check_max_abs_vs_jax": diffs,
        "training": {
            "config": cfg.to_dict(),
            "seed": cfg.seed,
            "command": command,
            "timings_s": {k: round(v, 1) for k, v in trainer.timings.items()},
            "hdr_maps": getattr(trainer, "hdr_names", []),
        },
        "evaluation": {},
    }
    if extra_meta:
        meta.update(extra_meta)
    return finalize_bundle(out, meta)


def finalize_bundle(out: Path, meta: dict) -> Path:
    """(Re)write bundle.json with the sha256 and size of every bundle file the folder holds (after
    evaluation adds figures, or ``illuminet bundle`` adds PRT tables)."""
    from illuminet.runtime.assets.bundle import FILES, METADATA

    out = Path(out)
    meta["files"] = {}
    for name in FILES.values():
        p = out / name
        if p.is_file():  # the ONNX pair and prt.npz are optional (load_bundle says which a bundle needs)
            meta["files"][name] = {"sha256": sha256(p), "bytes": p.stat().st_size}
    path = out / METADATA
    path.write_text(json.dumps(meta, indent=2) + "\n")
    return path
