"""Baseline keypoint transportation maps (numpy / scipy / scikit-learn only).

These re-implement the two maps of franzesegiovanni/gaussian_process_transportation
that kpflow's map benchmark compares against:

* ILWR, "iterative locally weighted translations" (their
  ``Iterative_Locally_Weighted_Translations``), after Perrin & Schlehuber-Caissier,
  "Fast diffeomorphic matching to learn globally asymptotically stable nonlinear
  dynamical systems", Systems & Control Letters 96 (2016).
* Residual GP transport (their ``GaussianProcessTransportation``): an sklearn
  ``GaussianProcessRegressor`` fitted on the displacement ``target - source``.

Both baselines leave out the authors' rigid (rotation + translation) pre-alignment
(``AffineTransform``); the maps are fitted on the raw keypoints.

Importing this module has no side effects. Run as a script, it times both baselines
single-threaded (``python benchmarks/baselines.py``).
"""

import os

if __name__ == "__main__":  # must precede the numpy import to take effect
    os.environ["OMP_NUM_THREADS"] = "1"

import numpy as np
from scipy.optimize import minimize
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

RHO_SAFE = np.sqrt(np.e / 2.0)  # rho * |v| < sqrt(e/2)  <=>  x + exp(-rho^2 |x-c|^2) v is a diffeomorphism


def ilwr_fit(source, target, n_steps=30, beta=0.9, rho_frac=0.99, tol=1e-12):
    """Fit ILWR (fast diffeomorphic matching) from ``source`` [N,D] to ``target`` [N,D].

    Each step moves the keypoint with the largest residual, p = argmax_i |target_i - z_i|:
    centre c = z_p, translation v = beta * (target_p - z_p), and
    psi(x) = x + exp(-rho^2 |x - c|^2) v, where rho in (0, rho_frac * sqrt(e/2) / |v|)
    minimises sum_i |target_i - psi(z_i)|^2 (L-BFGS-B, analytic gradient, started at a
    tenth of the bound as the authors do). Then z <- psi(z). Stops early once the largest
    residual is below ``tol`` (every later step would be a no-op).

    Returns a dict: ``c`` [K,D], ``v`` [K,D], ``rho`` [K] (K <= n_steps steps, in order)
    and the final keypoint residual ``residual_max`` / ``residual_rms`` of |target - z|.
    """
    z = np.array(source, dtype=float)
    target = np.asarray(target, dtype=float)
    cs, vs, rhos = [], [], []
    for _ in range(n_steps):
        r = target - z
        sq = np.einsum("nd,nd->n", r, r)
        p = int(np.argmax(sq))
        if sq[p] <= tol**2:
            break
        c, v = z[p].copy(), beta * r[p]
        vv = v @ v
        d2 = np.sum((z - c) ** 2, axis=1)
        rv = r @ v

        def loss(x):  # sum_i |r_i - w_i v|^2 with w_i = exp(-rho^2 d2_i), and d/drho
            rho = x[0]
            w = np.exp(-rho * rho * d2)
            g = w * vv - rv
            return np.sum(sq - 2.0 * w * rv + w * w * vv), np.array([-4.0 * rho * np.sum(g * w * d2)])

        rho_max = rho_frac * RHO_SAFE / np.sqrt(vv)
        rho = float(minimize(loss, [rho_max / 10.0], jac=True, method="L-BFGS-B", bounds=[(0.0, rho_max)]).x[0])
        z = z + np.exp(-rho * rho * d2)[:, None] * v
        cs.append(c), vs.append(v), rhos.append(rho)
    D = z.shape[1]
    res = np.linalg.norm(target - z, axis=1)
    return {
        "c": np.array(cs).reshape(-1, D),
        "v": np.array(vs).reshape(-1, D),
        "rho": np.array(rhos),
        "residual_max": float(res.max()),
        "residual_rms": float(np.sqrt(np.mean(res**2))),
    }


def ilwr_transport(params, x):
    """Apply the fitted ILWR steps, in order, to points ``x`` [M,D]; returns [M,D]."""
    y = np.array(x, dtype=float)
    for c, v, rho in zip(params["c"], params["v"], params["rho"]):
        y = y + np.exp(-rho * rho * np.sum((y - c) ** 2, axis=1))[:, None] * v
    return y


def sklearn_gp_fit(source, target, n_restarts=5, seed=0, normalize_y=False, kernel=None):
    """Fit the authors' residual GP map: GP regression of ``target - source`` on ``source``.

    Kernel as in their ``GaussianProcessTransportation`` default,
    ``C(0.1) * RBF(length_scale=[0.1]) + WhiteKernel(1e-4)`` with sklearn's default
    hyper-parameter bounds (1e-5, 1e5), isotropic RBF shared by all output dimensions,
    ``alpha=1e-10``, L-BFGS-B with ``n_restarts`` random restarts. The authors do not
    normalise y (sklearn's default, ``normalize_y=False``); pass ``normalize_y=True`` to standardise each output.
    ``kernel`` replaces the default (its last term must be the ``WhiteKernel``: the noise).
    Returns the fitted ``GaussianProcessRegressor``.
    """
    source = np.asarray(source, dtype=float)
    kernel = kernel if kernel is not None else ConstantKernel(0.1) * RBF(length_scale=[0.1]) + WhiteKernel(1e-4)
    gp = GaussianProcessRegressor(
        kernel=kernel, alpha=1e-10, n_restarts_optimizer=n_restarts, normalize_y=normalize_y, random_state=seed
    )
    return gp.fit(source, np.asarray(target, dtype=float) - source)


def sklearn_gp_transport(model, x):
    """Transport ``x`` [M,D] with a model from :func:`sklearn_gp_fit`.

    Returns ``(mean, std)``: mean = x + predicted displacement [M,D]; std [M,D] (or [M]
    for a single output) is the predictive std of the latent displacement, i.e. with the
    fitted white-noise variance removed. (The authors subtract sqrt(noise) from the std
    instead of removing the noise variance.)
    """
    x = np.asarray(x, dtype=float)
    mean, std = model.predict(x, return_std=True)
    noise = model.kernel_.k2.noise_level * np.asarray(model._y_train_std) ** 2
    std = np.sqrt(np.clip(std**2 - noise, 0.0, None))
    return x + mean.reshape(x.shape), std


def _problem(rng, n=25, m=20, amp=0.1):
    """25 source keypoints in [0,1]^2, target = source + smooth random displacement (~amp), 20 queries."""
    src = rng.uniform(size=(n, 2))
    W, phase = rng.normal(0.0, 2.0, size=(2, 2)), rng.uniform(0.0, 2 * np.pi, size=2)
    return src, src + amp * np.sin(src @ W + phase), rng.uniform(size=(m, 2))


if __name__ == "__main__":
    import time
    import warnings

    from sklearn.exceptions import ConvergenceWarning

    warnings.filterwarnings("ignore", category=ConvergenceWarning)
    reps = 50

    def ilwr(src, tgt, q):
        params = ilwr_fit(src, tgt)
        ilwr_transport(params, q)
        return lambda x: ilwr_transport(params, x)

    def gp(normalize_y):
        def run(src, tgt, q):
            model = sklearn_gp_fit(src, tgt, normalize_y=normalize_y)
            sklearn_gp_transport(model, q)
            return lambda x: sklearn_gp_transport(model, x)[0]

        return run

    print(f"25 keypoints in 2-D, fit + 20-point transport, median over {reps} random problems")
    print(f"{'method':30s} {'ms':>8s} {'res max':>10s} {'res rms':>10s}")
    for name, run in [
        ("ilwr (30 steps, beta=0.9)", ilwr),
        ("sklearn_gp (authors' setup)", gp(False)),
        ("sklearn_gp normalize_y=True", gp(True)),
    ]:
        ms, rmax, rrms = [], [], []
        for rep in range(reps + 1):  # rep 0 is a warm-up
            src, tgt, q = _problem(np.random.default_rng(rep))
            t0 = time.perf_counter()
            transport = run(src, tgt, q)
            dt = time.perf_counter() - t0
            res = np.linalg.norm(tgt - transport(src), axis=1)  # keypoint residual, untimed
            if rep:
                ms.append(dt * 1e3), rmax.append(res.max()), rrms.append(np.sqrt(np.mean(res**2)))
        print(f"{name:30s} {np.median(ms):8.2f} {np.median(rmax):10.2e} {np.median(rrms):10.2e}")
