"""Expected signatures of the ONNX models users download in the LightGlue-ONNX layouts.

C7 checks a model against one of these at load time (``InferenceRuntime.load_engine(path, signature)``)
so that a wrong or mis-exported file is refused at start-up with a message naming the tensor, never at
the first frame. Shapes below: ``B`` batch, ``C`` channels, ``H``/``W`` image size in px, ``N`` keypoints
per image, ``D`` descriptor size, ``M`` matches. ``None`` in a ``TensorSpec.shape`` = any size.

Separate extractor (DISK, ALIKED, XFeat exports)::

    image        (1, C, H, W)  float32   RGB (C=3) or grey (C=1), values in [0, 1]
    -> keypoints   (1, N, 2)   int64 or float32   pixel (x, y) in the input image
       scores      (1, N)      float32
       descriptors (1, N, D)   float32

    DISK: C=3, D=128. ALIKED: C=3, D=64 (aliked-t16/n16) or 128 (n32). XFeat: C=3 or 1, D=64.

LightGlue matcher::

    kpts0 (1, N0, 2) float32   keypoints normalised per image: (k - size/2) / (max(size)/2),
    kpts1 (1, N1, 2) float32   size = (w, h)  (see ``helpers.lightglue_runtime.normalize_keypoints``)
    desc0 (1, N0, D) float32
    desc1 (1, N1, D) float32
    -> matches0 (M, 2) int64    (index into kpts0, index into kpts1)
       mscores0 (M,)   float32  match confidence

Fused pipeline (extractor + LightGlue in one graph)::

    images (2B, C, H, W) float32   image pairs stacked: [img0_pair0, img1_pair0, img0_pair1, ...]
    -> keypoints (2B, N, 2) int64 (float32 accepted)   pixel (x, y)
       matches   (M, 3)     int64   (pair index b, index into keypoints[2b], index into keypoints[2b+1])
       mscores   (M,)       float32
"""

from __future__ import annotations

from gps_denied_onboard.helpers.inference_contract import EngineSignature, TensorSpec

#: Keypoint dtypes found in the wild: SuperPoint-style exports emit int64 pixels, others float32.
KEYPOINT_DTYPES = "int64|float32"


def extractor_signature(label: str, *, channels: int | None, descriptor_dim: int | None) -> EngineSignature:
    """Separate-extractor layout; ``channels``/``descriptor_dim`` None = any size."""
    return EngineSignature(
        label=label,
        inputs=(TensorSpec("image", 4, "float32", (1, channels, None, None)),),
        outputs=(
            TensorSpec("keypoints", 3, KEYPOINT_DTYPES, (1, None, 2)),
            TensorSpec("scores", 2, "float32", (1, None)),
            TensorSpec("descriptors", 3, "float32", (1, None, descriptor_dim)),
        ),
    )


def lightglue_matcher_signature(
    descriptor_dim: int | None = None, label: str = "lightglue"
) -> EngineSignature:
    """LightGlue matcher layout; ``descriptor_dim`` pins D when the extractor is known."""
    return EngineSignature(
        label=label,
        inputs=(
            TensorSpec("kpts0", 3, "float32", (1, None, 2)),
            TensorSpec("kpts1", 3, "float32", (1, None, 2)),
            TensorSpec("desc0", 3, "float32", (1, None, descriptor_dim)),
            TensorSpec("desc1", 3, "float32", (1, None, descriptor_dim)),
        ),
        outputs=(
            TensorSpec("matches0", 2, "int64", (None, 2)),
            TensorSpec("mscores0", 1, "float32", (None,)),
        ),
    )


def fused_pipeline_signature(
    channels: int | None = None, label: str = "lightglue_pipeline"
) -> EngineSignature:
    """Fused extractor+LightGlue layout (``images`` -> ``keypoints``, ``matches``, ``mscores``)."""
    return EngineSignature(
        label=label,
        inputs=(TensorSpec("images", 4, "float32", (None, channels, None, None)),),
        outputs=(
            TensorSpec("keypoints", 3, KEYPOINT_DTYPES, (None, None, 2)),
            TensorSpec("matches", 2, "int64", (None, 3)),
            TensorSpec("mscores", 1, "float32", (None,)),
        ),
    )


#: DISK extractor: RGB in, 128-d descriptors.
DISK_EXTRACTOR = extractor_signature("disk", channels=3, descriptor_dim=128)
#: ALIKED extractor: RGB in, 64-d (t16/n16) or 128-d (n32) descriptors.
ALIKED_EXTRACTOR = extractor_signature("aliked", channels=3, descriptor_dim=None)
#: XFeat extractor: RGB or grey in, 64-d descriptors.
XFEAT_EXTRACTOR = extractor_signature("xfeat", channels=None, descriptor_dim=64)
#: LightGlue matcher for any descriptor size (use ``lightglue_matcher_signature(128)`` to pin D).
LIGHTGLUE_MATCHER = lightglue_matcher_signature()
#: LightGlue matcher trained on DISK features (D=128).
DISK_LIGHTGLUE_MATCHER = lightglue_matcher_signature(128, label="disk_lightglue")
#: Fused extractor+matcher pipeline.
FUSED_PIPELINE = fused_pipeline_signature()
