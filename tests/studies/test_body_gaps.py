"""The study's gap finder (benchmarks/body_gaps.py): a body that lacks a known piece of its target
is reported with that piece (its size, centre and depth) and the voxels it puts outside; a body of
higher genus than its target, with the piece that carries the surplus (a tear or a bridge)."""

import numpy as np
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
    assert len(out) == 3, out  # one missing piece, then the genus of both (no surplus: nothing more)
    # its centre (2.0, 2.0, 3.5); its deepest voxels are the lower layer's middle ones, two voxels
    # below the target's top face and more from its sides
    assert out[1] == "  missing piece of 128 voxels at (2.0, 2.0, 3.5), 2.0 voxels deep", out[1]
    assert out[2] == "genus of the solids: body 0, target 0", out[2]


def test_a_tear_and_a_bridge_are_named_as_the_pieces_that_carry_the_genus(capsys):
    """A column of voxels missing through a block (a tear: the body's genus 1, the block's 0) is the
    missing piece whose filling lowers it; a bar closing a U (a bridge) is the piece outside the
    target whose removal does (what lies within two voxels of the target is not counted)."""
    axes = [np.arange(12) + 0.5] * 3
    block = np.zeros((12, 12, 12), bool)
    block[2:10, 2:10, 2:10] = True
    torn = block.copy()
    torn[5:7, 5:7, 2:10] = False
    body_gaps.genus_carriers(torn, block, axes)
    out = capsys.readouterr().out.splitlines()
    assert out == ["genus of the solids: body 1, target 0",
                   "  missing piece of 32 voxels at (6.0, 6.0, 6.0), spanning 1.0 x 1.0 x 7.0: the body's genus 1 -> 0"], out
    u = np.zeros((12, 12, 12), bool)
    u[0:2, 0:12, 0:2] = u[10:12, 0:12, 0:2] = u[0:12, 0:2, 0:2] = True
    bridged = u.copy()
    bridged[2:10, 10:12, 0:2] = True
    body_gaps.genus_carriers(bridged, u, axes)
    out = capsys.readouterr().out.splitlines()
    assert out == ["genus of the solids: body 1, target 0",
                   "  outside piece of 16 voxels at (6.0, 11.0, 1.0), spanning 3.0 x 1.0 x 1.0: the body's genus 1 -> 0"], out
