"""Differentiable Gaussian splatting renderer and rendering losses (paper sections 3.2, 3.5).

Each surface particle is a 3D Gaussian with mean x_i and covariance Sigma_i = sigma0^2 F_i F_i^T
(MPM-Gaussian duality). Pipeline and where each piece lives:

- projection.py (torch): F -> Sigma, EWA projection Sigma2D = J W Sigma W^T J^T + low_pass I,
  its inverse (the conic), culling of Gaussians behind the near plane or off screen; a
  hand-written reverse, tested against autograd through the forward.
- tiles.py: duplicate each visible Gaussian once per screen tile its 3-sigma box touches and
  sort by (tile, depth): memory O(pixels + pairs), never O(pixels x Gaussians).
- rasterizer.py (Taichi): front-to-back compositing of alpha = 1 - T_final and accumulated depth
  D = sum a_k T_k z_k, with a hand-written backward (back to front, as 3DGS). Two loop orders
  with identical results: Gaussian-major per tile (CPU default) and pixel-parallel (CUDA).
- dense.py: the obviously-correct dense reference (every pixel x every Gaussian, autograd).
- losses.py: L_DT = mean(alpha * sdt / H) (resolution independent), soft IoU, depth MSE on
  target-covered pixels (torch, by autograd: the reference), their gradients in closed form a view
  at a time (what the renderer runs), adaptive gradient matching, alpha MSE metric.
- api.py: render_and_grad (losses + dL/dF [+ dL/dx]), render_views (forward), coverage_behind
  (forward behind a given transmittance), shade (Phong).

Runs on CPU, or CUDA with ``RenderConfig(device="cuda"|"auto")``; the Taichi runtime is shared
with the MPM solver through :func:`physmorph.base.taichi_runtime.init_taichi` (one arch per process).

May import physmorph.settings and physmorph.base; not the solver, the plasticity or the morph loop.
"""
