"""Transport a demonstrated trajectory into a new scene through a map fitted on a few keypoints.

A 2-D reach from a start box to a goal box is demonstrated once. In a new scene both boxes have moved and turned;
an ILWR map and a GP map fitted on the boxes' corners carry the demonstration there: positions by phi, velocities by
its Jacobian, orientations by the Jacobian's polar factor, with the GP's uncertainty along the way.

    python -m kpflow.examples.transport_trajectory     # prints a few numbers, writes transport_trajectory.png here

This file is also the tutorial docs/tutorials/transport.md (its code blocks are these sections).
"""

# --8<-- [start:scene]
import math

import matplotlib.pyplot as plt
import torch

from kpflow.maps import GPMap, ILWRMap
from kpflow.transport import transport_trajectory

torch.set_default_dtype(torch.float64)  # float64 throughout: the maps follow the dtype of their inputs


def rotation(angle):
    """2-D rotation matrices [..., 2, 2] for angles [...] in radians."""
    angle = torch.as_tensor(angle)
    c, s = torch.cos(angle), torch.sin(angle)
    return torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], -2)


def box_corners(centre, angle_deg, half=0.3):
    """The 4 corners [4, 2] of a square box: the keypoints a camera or a tag would give."""
    corners = torch.tensor([[-half, -half], [half, -half], [half, half], [-half, half]])
    return corners @ rotation(math.radians(angle_deg)).T + torch.tensor(centre)


# the demonstration's scene: start box at the origin, goal box 4 units to the right
source = torch.cat([box_corners([0.0, 0.0], 0), box_corners([4.0, 0.0], 0)])  # [8, 2]
# a new scene: the start box moved a little and turned by 10 degrees, the goal box moved up and turned by -45 degrees
target = torch.cat([box_corners([0.2, -0.3], 10), box_corners([3.6, 1.0], -45)])  # [8, 2]
# --8<-- [end:scene]

# --8<-- [start:demo]
# the demonstration: an S-shaped reach from the start box to the goal box with minimum-jerk timing (at rest at both
# ends), its velocities, and a gripper orientation that turns from 0 to 90 degrees on the way
t = torch.linspace(0.0, 1.0, 200)
s = 10 * t**3 - 15 * t**4 + 6 * t**5  # progress along the path, 0 -> 1
ds = 30 * t**2 - 60 * t**3 + 30 * t**4  # its time derivative
start, goal = torch.tensor([0.0, 0.0]), torch.tensor([4.0, 0.0])
side = torch.tensor([0.0, 1.0])  # the S swings 0.8 to each side
positions = start + s[:, None] * (goal - start) + 0.8 * torch.sin(2 * math.pi * s)[:, None] * side  # [200, 2]
velocities = ds[:, None] * ((goal - start) + 0.8 * 2 * math.pi * torch.cos(2 * math.pi * s)[:, None] * side)
orientations = rotation(math.pi / 2 * s)  # [200, 2, 2]
# --8<-- [end:demo]

# --8<-- [start:fit]
ilwr = ILWRMap().fit(source, target)  # 30 locally weighted translations after a rigid fit; exact inverse
gp = GPMap().fit(source, target)  # a GP on the residual of the rigid fit; posterior variance

for name, phi in (("ILWR", ilwr), ("GP", gp)):
    residual = (phi(source) - target).norm(dim=-1).max()
    print(f"{name}: largest keypoint residual |phi(s) - t| = {residual:.2e}")
# --8<-- [end:fit]

# --8<-- [start:transport]
moved = transport_trajectory(ilwr, positions, velocities, orientations)
# moved.positions [200, 2] = phi(x); moved.velocities = J(x) v; moved.orientations = polar(J(x)) R; moved.std

# the transported path starts at the new start box and ends at the new goal box
print(f"path start -> new start box: {(moved.positions[0] - target[:4].mean(0)).norm():.3f}")
print(f"path end   -> new goal box:  {(moved.positions[-1] - target[4:].mean(0)).norm():.3f}")

# a velocity v at x moves to J(x) v: the derivative of phi along v (here against a central difference)
h = 1e-6
along = (ilwr(positions + h * velocities) - ilwr(positions - h * velocities)) / (2 * h)
error = (moved.velocities - along).norm(dim=-1).max() / moved.velocities.norm(dim=-1).max()
print(f"J(x) v against the central difference of phi along v: {error:.1e} of the top speed")


def degrees(r):
    return math.degrees(math.atan2(r[1, 0], r[0, 0]))


# orientations turn with the map where the path is: by the start box's 10 degrees at the start; at the end, the goal
# box turned by -45 degrees, but the map is one smooth deformation of the whole plane fitted on both boxes, so there
# it turns the demonstration's final 90 degrees by less than the box itself (to about 38 rather than 45)
print(
    f"orientation at the start: {degrees(orientations[0]):.1f} deg demonstrated, "
    f"{degrees(moved.orientations[0]):.1f} deg transported"
)
print(
    f"orientation at the end:   {degrees(orientations[-1]):.1f} deg demonstrated, "
    f"{degrees(moved.orientations[-1]):.1f} deg transported"
)

# ILWR's inverse is exact: back to the demonstration
print(f"ILWR inverse: max |phi^-1(phi(x)) - x| = {(ilwr.inverse(moved.positions) - positions).abs().max():.1e}")
# --8<-- [end:transport]

# --8<-- [start:uncertainty]
gp_moved = transport_trajectory(gp, positions, velocities, n_samples=20, generator=torch.Generator().manual_seed(0))
std = gp_moved.std.norm(dim=-1)  # [200]: the GP's standard deviation of phi(x) at each point
far = gp.predict(torch.tensor([[20.0, 20.0]]))[1].sqrt().norm()
print(
    f"GP std: {gp.predict(source)[1].sqrt().norm(dim=-1).max():.1e} at the keypoints, "
    f"{std[0]:.3f} at the path's start, {std.max():.3f} at most along it, {far:.3f} far from every keypoint"
)
print(f"ILWR and GP paths differ by {(moved.positions - gp_moved.positions).norm(dim=-1).max():.3f} at most")
# --8<-- [end:uncertainty]

# --8<-- [start:plot]
fig, axes = plt.subplots(1, 2, figsize=(12, 4.2), sharex=True, sharey=True)
axes[0].plot(*positions.T, "k-", label="demonstration")
axes[0].scatter(*source.T, c="tab:blue", label="source keypoints")
axes[1].plot(*moved.positions.T, "tab:green", label="ILWR")
axes[1].plot(*gp_moved.positions.T, "tab:orange", label="GP mean")
for sample in gp_moved.samples:  # [20, 200, 2]: 20 maps drawn from the GP's posterior
    axes[1].plot(*sample.T, color="tab:orange", alpha=0.3, lw=0.6)
# the GP's 2-sigma band: the region inside some path point's 2-sigma ellipse (semi-axes 2 std of each coordinate),
# the level 1 of its smallest normalised distance to the path, drawn as one smooth filled contour
gx, gy = torch.meshgrid(torch.linspace(-0.6, 4.6, 260), torch.linspace(-1.0, 1.7, 140), indexing="xy")
grid = torch.stack([gx, gy], -1).reshape(-1, 1, 2)  # [G, 1, 2]
reach = ((grid - gp_moved.positions) / (2.0 * gp_moved.std)).norm(dim=-1).min(dim=1).values  # [G]
axes[1].contourf(gx, gy, reach.reshape(gx.shape), levels=[0.0, 1.0], colors="tab:orange", alpha=0.18)
axes[1].contour(gx, gy, reach.reshape(gx.shape), levels=[1.0], colors="tab:orange", linewidths=0.8, alpha=0.6)
axes[1].plot([], [], color="tab:orange", lw=6, alpha=0.25, label="GP 2-sigma band")  # the band's legend entry
axes[1].scatter(*target.T, c="tab:red", label="target keypoints")
for ax, x, r in ((axes[0], positions, orientations), (axes[1], moved.positions, moved.orientations)):
    ax.quiver(
        *x[::25].T, *r[::25, :, 0].T, angles="xy", scale_units="xy", scale=3, width=0.004, color="0.3"
    )  # the gripper's x axis
for ax, title in zip(axes, ("demonstrated scene", "new scene")):
    ax.set_title(title)
    ax.set_aspect("equal")
    ax.set_xlabel("x (scene units; a box is 0.6 wide)")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
axes[0].set_ylabel("y (scene units)")
fig.tight_layout()
fig.savefig("transport_trajectory.png", dpi=120, bbox_inches="tight")
print("wrote transport_trajectory.png")
# --8<-- [end:plot]
