"""Files made from a calibration and its take: BVH, the glTF 2.0 (VRM) rig, TRC joint centres, the HTML report,
the skeleton file."""

from flockcal.lazy import public_api

# What a user of the exports reaches for, each loaded on first use (tests/test_public_api.py resolves them).
__getattr__, __dir__, __all__ = public_api(__name__, {
    "write_bvh": "flockcal.exports.bvh",
    "bvh_text": "flockcal.exports.bvh",
    "bvh_chunks": "flockcal.exports.bvh",
    "write_gltf": "flockcal.exports.gltf",
    "gltf_bytes": "flockcal.exports.gltf",
    "glb_chunks": "flockcal.exports.gltf",
    "write_trc": "flockcal.exports.trc",
    "trc_text": "flockcal.exports.trc",
    "write_report": "flockcal.exports.report",
    "report_html": "flockcal.exports.report",
    "write_skeleton": "flockcal.exports.skeleton",
    "skeleton_bytes": "flockcal.exports.skeleton",
    "load_skeleton": "flockcal.exports.skeleton",
    "parse_skeleton": "flockcal.exports.skeleton",
})
