"""The study's gap finder (benchmarks/body_gaps.py): a body that lacks a known piece of its target
is reported with that piece (its size, centre and depth) and the voxels it puts outside."""

import trimesh

from benchmark_scripts import load_benchmark

body_gaps = load_benchmark("body_gaps")


def test_a_missing_slab_is_found_with_its_size_centre_and_depth(capsys):
    # target: the box [0, 4]^3; body: [0, 5] x [0, 4] x [0, 3], which lacks the target's top slab
    # z in [3, 4] and puts [4, 5] x [0, 4] x [0, 3] outside it. Voxels of 0.5: the target 8^3 = 512,
    # the body 10 x 8 x 6 = 480, both 8 x 8 x 6 = 384 (IoU 384 / 608); missing 8 x 8 x 2 = 128, outside 2 x 8 x 6 = 96.
    target = trimesh.creation.box(bounds=[[0, 0, 0], [4, 4, 4]])
    body = trimesh.creation.box(bounds=[[0, 0, 0], [5, 4, 3]])
    body_gaps.missing_pieces(body, target, voxel=0.5, shown=3)
    out = capsys.readouterr().out.splitlines()
    assert out[0] == ("voxels of 0.5: target 512, body 480, IoU 0.632, inside the target and not the body 128, "
                      "in the body outside the target 96"), out[0]
    assert len(out) == 2, out  # one missing piece
    # its centre (2.0, 2.0, 3.5); its deepest voxels are the lower layer's middle ones, two voxels
    # below the target's top face and more from its sides
    assert out[1] == "  missing piece of 128 voxels at (2.0, 2.0, 3.5), 2.0 voxels deep", out[1]
