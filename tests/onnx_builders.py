"""Small but real ONNX models in the LightGlue-ONNX layouts, built with ``onnx.helper`` (no torch).

Pretrained DISK/LightGlue weights are not available offline, so the runtime path is exercised with
models that have the exact input/output signatures and a deterministic, image-dependent computation:

* extractor: grey = mean over channels; an 8x8/stride-4 convolution with a fixed random zero-mean
  kernel bank gives one D-dim descriptor per grid cell (a random projection of the patch); the
  response is the descriptor energy; the top-N cells (``TopK``, N = min(max_keypoints, cells), so N
  depends on H and W) become keypoints at the patch centre, descriptors L2-normalised. Two copies of
  an image shifted by a multiple of 4 px therefore produce identical descriptors at shifted keypoints.
* matcher: cosine similarity, mutual argmax, similarity threshold, ``NonZero`` -> dynamic M (may be 0).
* fused pipeline: the extractor over a (2B, C, H, W) batch, pairs reshaped to (B, 2, ...) (an odd
  batch fails at run time), matched as above with a (batch, idx0, idx1) layout.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17
IR_VERSION = 8
PATCH_PX = 8
STRIDE_PX = 4
#: Keypoint = patch centre: x = STRIDE_PX * col + offset (3.5 for float32 keypoints, 3 for int64).
CENTRE_OFFSET_FLOAT = 3.5
CENTRE_OFFSET_INT = 3

_NP_TO_ONNX = {
    np.dtype("float32"): TensorProto.FLOAT,
    np.dtype("float16"): TensorProto.FLOAT16,
    np.dtype("float64"): TensorProto.DOUBLE,
    np.dtype("int64"): TensorProto.INT64,
    np.dtype("int32"): TensorProto.INT32,
    np.dtype("uint8"): TensorProto.UINT8,
    np.dtype("bool"): TensorProto.BOOL,
}

Dim = int | str | None


class _Graph:
    """Tiny graph-building helper: unique names, constants as initializers."""

    def __init__(self) -> None:
        self.nodes: list[onnx.NodeProto] = []
        self.initializers: list[onnx.TensorProto] = []
        self._n = 0

    def _name(self, hint: str) -> str:
        self._n += 1
        return f"{hint}_{self._n}"

    def const(
        self, value: np.ndarray | Sequence[float] | float, dtype: str = "int64", hint: str = "c"
    ) -> str:
        name = self._name(hint)
        self.initializers.append(numpy_helper.from_array(np.asarray(value, dtype=dtype), name))
        return name

    def op(self, op_type: str, inputs: Sequence[str], out: str | None = None, n_out: int = 1, **attrs) -> str:
        if n_out == 1:
            outs = [out or self._name(op_type.lower())]
        else:
            outs = [self._name(op_type.lower()) for _ in range(n_out)]
        self.nodes.append(helper.make_node(op_type, list(inputs), outs, **attrs))
        return outs[0] if n_out == 1 else outs  # type: ignore[return-value]

    def op2(self, op_type: str, inputs: Sequence[str], outs: Sequence[str], **attrs) -> None:
        self.nodes.append(helper.make_node(op_type, list(inputs), list(outs), **attrs))


def _value_info(name: str, dtype: str, shape: Sequence[Dim] | None) -> onnx.ValueInfoProto:
    elem = TensorProto.STRING if dtype == "string" else _NP_TO_ONNX[np.dtype(dtype)]
    if shape is None:
        return helper.make_tensor_value_info(name, elem, None)
    return helper.make_tensor_value_info(name, elem, list(shape))


def _save(
    g: _Graph,
    path: str | Path,
    inputs: Sequence[onnx.ValueInfoProto],
    outputs: Sequence[onnx.ValueInfoProto],
    name: str,
) -> Path:
    graph = helper.make_graph(g.nodes, name, list(inputs), list(outputs), initializer=g.initializers)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="tests")
    model.ir_version = IR_VERSION
    onnx.checker.check_model(model)
    path = Path(path)
    onnx.save(model, str(path))
    return path


def _l2_normalise(g: _Graph, x: str, axis: int) -> str:
    sq = g.op("ReduceSumSquare", [x], axes=[axis], keepdims=1)
    norm = g.op("Sqrt", [g.op("Add", [sq, g.const(1e-12, "float32")])])
    return g.op("Div", [x, norm])


def _descriptor_kernel(dim: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    k = rng.standard_normal((dim, PATCH_PX * PATCH_PX)).astype(np.float32)
    k -= k.mean(axis=1, keepdims=True)  # zero-mean: descriptors ignore a brightness offset
    return (k / PATCH_PX).reshape(dim, 1, PATCH_PX, PATCH_PX)


def _extract(
    g: _Graph, image: str, *, dim: int, max_keypoints: int, keypoint_dtype: str, seed: int
) -> tuple[str, str, str]:
    """Extractor sub-graph on (B, C, H, W) -> keypoints (B, N, 2), scores (B, N), descriptors (B, N, D)."""
    grey = g.op("ReduceMean", [image], axes=[1], keepdims=1)
    dmap = g.op(
        "Conv",
        [grey, g.const(_descriptor_kernel(dim, seed), "float32", "w_desc")],
        kernel_shape=[PATCH_PX, PATCH_PX],
        strides=[STRIDE_PX, STRIDE_PX],
    )  # (B, D, Hc, Wc)
    resp = g.op("ReduceSumSquare", [dmap], axes=[1], keepdims=0)  # (B, Hc, Wc)
    resp_flat = g.op("Reshape", [resp, g.const([0, -1])])  # (B, P)
    cells = g.op("Shape", [resp_flat], start=1, end=2)  # (1,) = P
    k = g.op("Min", [g.const([max_keypoints]), cells])
    scores_raw, idx = g.op("TopK", [resp_flat, k], n_out=2, axis=1, largest=1, sorted=1)
    width = g.op("Shape", [dmap], start=3, end=4)  # (1,) = Wc
    col = g.op("Mod", [idx, width])
    row = g.op("Div", [idx, width])
    xy = g.op(
        "Concat",
        [g.op("Unsqueeze", [col, g.const([2])]), g.op("Unsqueeze", [row, g.const([2])])],
        axis=2,
    )  # (B, N, 2) int64 grid cells
    if keypoint_dtype == "int64":
        kpts = g.op("Add", [g.op("Mul", [xy, g.const(STRIDE_PX)]), g.const(CENTRE_OFFSET_INT)])
    else:
        xy_f = g.op("Cast", [xy], to=TensorProto.FLOAT)
        kpts = g.op(
            "Add",
            [g.op("Mul", [xy_f, g.const(STRIDE_PX, "float32")]), g.const(CENTRE_OFFSET_FLOAT, "float32")],
        )
    dflat = g.op("Reshape", [dmap, g.const([0, 0, -1])])  # (B, D, P)
    dT = g.op("Transpose", [dflat], perm=[0, 2, 1])  # (B, P, D)
    idx3 = g.op("Unsqueeze", [idx, g.const([2])])  # (B, N, 1)
    gather_shape = g.op("Concat", [g.op("Shape", [idx]), g.const([dim])], axis=0)
    idx_exp = g.op("Expand", [idx3, gather_shape])  # (B, N, D)
    desc = _l2_normalise(g, g.op("GatherElements", [dT, idx_exp], axis=1), axis=2)
    scores = g.op("Div", [scores_raw, g.const(float(dim), "float32")])
    return kpts, scores, desc


def build_fake_extractor(
    path: str | Path,
    *,
    channels: int = 3,
    dim: int = 128,
    num_keypoints: int = 256,
    keypoint_dtype: str = "int64",
    seed: int = 7,
) -> Path:
    """Separate-extractor layout: ``image`` (1,C,H,W) -> keypoints (1,N,2), scores, descriptors (1,N,D).

    N = min(num_keypoints, ((H-8)//4+1) * ((W-8)//4+1)); images smaller than 8 px fail at run time.
    """
    g = _Graph()
    kpts, scores, desc = _extract(
        g, "image", dim=dim, max_keypoints=num_keypoints, keypoint_dtype=keypoint_dtype, seed=seed
    )
    g.op("Identity", [kpts], out="keypoints")
    g.op("Identity", [scores], out="scores")
    g.op("Identity", [desc], out="descriptors")
    return _save(
        g,
        path,
        [_value_info("image", "float32", [1, channels, "H", "W"])],
        [
            _value_info("keypoints", keypoint_dtype, [1, "N", 2]),
            _value_info("scores", "float32", [1, "N"]),
            _value_info("descriptors", "float32", [1, "N", dim]),
        ],
        "fake_extractor",
    )


def _mutual_nn(g: _Graph, sim: str, n0_axis_len: str, min_similarity: float) -> tuple[str, str, str]:
    """On sim (N0, N1): returns i (M,), j (M,), score (M,) for mutual best pairs above the threshold."""
    nn01 = g.op("ArgMax", [sim], axis=1, keepdims=0)  # (N0,)
    best = g.op("ReduceMax", [sim], axes=[1], keepdims=0)  # (N0,)
    nn10 = g.op("ArgMax", [sim], axis=0, keepdims=0)  # (N1,)
    back = g.op("Gather", [nn10, nn01], axis=0)  # (N0,)
    arange = g.op("Range", [g.const(0), n0_axis_len, g.const(1)])
    mutual = g.op("Equal", [back, arange])
    strong = g.op("Greater", [best, g.const(min_similarity, "float32")])
    keep = g.op("And", [mutual, strong])
    i = g.op("Squeeze", [g.op("NonZero", [keep]), g.const([0])])  # (M,)
    j = g.op("Gather", [nn01, i], axis=0)
    score = g.op("Gather", [best, i], axis=0)
    return i, j, score


def build_fake_lightglue(
    path: str | Path,
    dim: int = 128,
    *,
    min_similarity: float = 0.5,
    echo_inputs: bool = False,
    require_even_n0: bool = False,
) -> Path:
    """Matcher layout: kpts0/kpts1 (1,N,2), desc0/desc1 (1,N,D) -> matches0 (M,2) int64, mscores0 (M,).

    Mutual nearest neighbours on cosine similarity > ``min_similarity`` (M may be 0).
    ``echo_inputs`` adds outputs ``echo_kpts0``/``echo_kpts1`` (the keypoints exactly as received).
    ``require_even_n0`` makes the model fail at run time when N0 is odd (a Reshape to (-1, 2, 2)).
    """
    g = _Graph()
    d0 = _l2_normalise(g, "desc0", axis=2)
    d1 = _l2_normalise(g, "desc1", axis=2)
    sim3 = g.op("MatMul", [d0, g.op("Transpose", [d1], perm=[0, 2, 1])])  # (1, N0, N1)
    sim = g.op("Squeeze", [sim3, g.const([0])])
    n0 = g.op("Squeeze", [g.op("Shape", ["desc0"], start=1, end=2), g.const([0])])
    i, j, score = _mutual_nn(g, sim, n0, min_similarity)
    g.op(
        "Concat",
        [g.op("Unsqueeze", [i, g.const([1])]), g.op("Unsqueeze", [j, g.const([1])])],
        out="matches0",
        axis=1,
    )
    # Keypoints only feed the output through a zero term: the fake matches on descriptors alone, but
    # the inputs stay live in the graph.
    kp_term = g.op(
        "Mul",
        [
            g.op("Add", [g.op("ReduceSum", ["kpts0"], keepdims=0), g.op("ReduceSum", ["kpts1"], keepdims=0)]),
            g.const(0.0, "float32"),
        ],
    )
    if require_even_n0:
        pairs = g.op("Reshape", ["kpts0", g.const([-1, 2, 2])])
        kp_term = g.op(
            "Add", [kp_term, g.op("Mul", [g.op("ReduceSum", [pairs], keepdims=0), g.const(0.0, "float32")])]
        )
    g.op("Add", [score, kp_term], out="mscores0")
    outputs = [
        _value_info("matches0", "int64", ["M", 2]),
        _value_info("mscores0", "float32", ["M"]),
    ]
    if echo_inputs:
        g.op("Identity", ["kpts0"], out="echo_kpts0")
        g.op("Identity", ["kpts1"], out="echo_kpts1")
        outputs += [
            _value_info("echo_kpts0", "float32", [1, "N0", 2]),
            _value_info("echo_kpts1", "float32", [1, "N1", 2]),
        ]
    return _save(
        g,
        path,
        [
            _value_info("kpts0", "float32", [1, "N0", 2]),
            _value_info("kpts1", "float32", [1, "N1", 2]),
            _value_info("desc0", "float32", [1, "N0", dim]),
            _value_info("desc1", "float32", [1, "N1", dim]),
        ],
        outputs,
        "fake_lightglue",
    )


def build_constant_matcher(path: str | Path, matches: np.ndarray, scores: np.ndarray, dim: int = 128) -> Path:
    """Matcher layout whose outputs are fixed (out-of-range indices, score filtering tests)."""
    g = _Graph()
    zero = g.op(
        "Mul",
        [
            g.op("ReduceSum", [g.op("Concat", ["kpts0", "kpts1"], axis=1)], keepdims=0),
            g.const(0.0, "float32"),
        ],
    )
    zero_d = g.op(
        "Mul",
        [
            g.op("ReduceSum", [g.op("Concat", ["desc0", "desc1"], axis=1)], keepdims=0),
            g.const(0.0, "float32"),
        ],
    )
    g.op("Identity", [g.const(np.asarray(matches, dtype=np.int64).reshape(-1, 2))], out="matches0")
    g.op("Add", [g.op("Add", [g.const(np.asarray(scores), "float32"), zero]), zero_d], out="mscores0")
    return _save(
        g,
        path,
        [
            _value_info("kpts0", "float32", [1, "N0", 2]),
            _value_info("kpts1", "float32", [1, "N1", 2]),
            _value_info("desc0", "float32", [1, "N0", dim]),
            _value_info("desc1", "float32", [1, "N1", dim]),
        ],
        [_value_info("matches0", "int64", ["M", 2]), _value_info("mscores0", "float32", ["M"])],
        "constant_matcher",
    )


def build_fused_pipeline(
    path: str | Path,
    *,
    channels: int = 3,
    dim: int = 64,
    num_keypoints: int = 128,
    min_similarity: float = 0.5,
    seed: int = 7,
) -> Path:
    """Fused layout: ``images`` (2B,C,H,W) -> keypoints (2B,N,2) int64, matches (M,3) int64, mscores (M,).

    Pairs are (images[2b], images[2b+1]); an odd leading dimension fails at run time (Reshape).
    """
    g = _Graph()
    kpts, _scores, desc = _extract(
        g, "images", dim=dim, max_keypoints=num_keypoints, keypoint_dtype="int64", seed=seed
    )
    g.op("Identity", [kpts], out="keypoints")
    pair_shape = g.op("Concat", [g.const([-1, 2]), g.op("Shape", [desc], start=1)], axis=0)
    pairs = g.op("Reshape", [desc, pair_shape])  # (B, 2, N, D)
    d0 = g.op("Gather", [pairs, g.const(0)], axis=1)  # (B, N, D)
    d1 = g.op("Gather", [pairs, g.const(1)], axis=1)
    sim = g.op("MatMul", [d0, g.op("Transpose", [d1], perm=[0, 2, 1])])  # (B, N, N)
    nn01 = g.op("ArgMax", [sim], axis=2, keepdims=0)  # (B, N)
    best = g.op("ReduceMax", [sim], axes=[2], keepdims=0)
    nn10 = g.op("ArgMax", [sim], axis=1, keepdims=0)
    back = g.op("GatherElements", [nn10, nn01], axis=1)
    n = g.op("Squeeze", [g.op("Shape", [desc], start=1, end=2), g.const([0])])
    arange = g.op("Range", [g.const(0), n, g.const(1)])
    keep = g.op(
        "And",
        [g.op("Equal", [back, arange]), g.op("Greater", [best, g.const(min_similarity, "float32")])],
    )
    bi = g.op("Transpose", [g.op("NonZero", [keep])], perm=[1, 0])  # (M, 2) = (b, i)
    j = g.op("GatherND", [nn01, bi])  # (M,)
    g.op("Concat", [bi, g.op("Unsqueeze", [j, g.const([1])])], out="matches", axis=1)
    g.op("GatherND", [best, bi], out="mscores")
    return _save(
        g,
        path,
        [_value_info("images", "float32", ["2B", channels, "H", "W"])],
        [
            _value_info("keypoints", "int64", ["2B", "N", 2]),
            _value_info("matches", "int64", ["M", 3]),
            _value_info("mscores", "float32", ["M"]),
        ],
        "fake_fused_pipeline",
    )


def build_stub_model(
    path: str | Path,
    inputs: Sequence[tuple[str, str, Sequence[Dim] | None]],
    outputs: Sequence[tuple[str, str, Sequence[Dim]]],
) -> Path:
    """A valid model with the declared inputs/outputs (outputs are constant-filled; for signature tests).

    Each entry is (name, numpy dtype name or ``"string"`` for inputs, shape); str/None dims are
    dynamic. Inputs are not consumed; ONNX Runtime still declares and requires them.
    """
    g = _Graph()
    for name, dtype, shape in outputs:
        dims = [d if isinstance(d, int) else 1 for d in shape]
        value = helper.make_tensor("value", _NP_TO_ONNX[np.dtype(dtype)], [1], [0])
        g.op("ConstantOfShape", [g.const(dims)], out=name, value=value)
    return _save(
        g,
        path,
        [_value_info(n, d, s) for n, d, s in inputs],
        [_value_info(n, d, s) for n, d, s in outputs],
        "stub",
    )


def build_disk_like_stub(
    path: str | Path,
    *,
    keypoints: tuple[str, str, Sequence[Dim]] = ("keypoints", "int64", [1, "N", 2]),
    scores: tuple[str, str, Sequence[Dim]] | None = ("scores", "float32", [1, "N"]),
    descriptors: tuple[str, str, Sequence[Dim]] = ("descriptors", "float32", [1, "N", 128]),
    image: tuple[str, str, Sequence[Dim]] = ("image", "float32", [1, 3, "H", "W"]),
    extra_inputs: Sequence[tuple[str, str, Sequence[Dim]]] = (),
    extra_outputs: Sequence[tuple[str, str, Sequence[Dim]]] = (),
) -> Path:
    """DISK-extractor-shaped stub; override one tensor to build a wrong-signature variant."""
    outs = [keypoints, *([scores] if scores is not None else []), descriptors, *extra_outputs]
    return build_stub_model(path, [image, *extra_inputs], outs)


def build_reshape_model(path: str | Path) -> Path:
    """``x`` (1, n) float32 -> ``y`` (n/3, 3): fails at run time unless n is a multiple of 3."""
    g = _Graph()
    g.op("Reshape", ["x", g.const([-1, 3])], out="y")
    return _save(
        g,
        path,
        [_value_info("x", "float32", [1, "n"])],
        [_value_info("y", "float32", [None, 3])],
        "reshape",
    )
