"""Pad forces over one episode: the picture to look at when a grasp fails.

``TactileTrace`` records |F| of the 11 pads of one world every control step until that world's first
episode ends; ``plot`` draws one panel per finger with the phases shaded.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from d3grasp.dexhand13 import FINGER_PADS, FINGERS

PHASE_SHADES = {
    "approach": "#f0f0f0",
    "grasp": "#e3eefa",
    "lift": "#e6f5e3",
    "hold": "#fdf3dc",
    "disturb": "#fbe3e1",
    "release": "#eeeeee",
}


class TactileTrace:
    """Per-step pad force magnitudes (true contact forces or the noisy sensor) of one world."""

    def __init__(self, env, world: int = 0, sensed: bool = False) -> None:
        if not 0 <= world < env.num_envs:
            raise ValueError(f"tactile plot world must lie in [0, {env.num_envs}), got {world}")
        self.env, self.world, self.sensed = env, int(world), sensed
        self.forces: list[np.ndarray] = []
        self.done = False
        self.meta: dict[str, str] = {}
        self.outcome: dict | None = None

    def record(self, episodes: list[dict] | None = None) -> None:
        """Call after every env.step with that step's finished episodes (extras['episodes'])."""
        if self.done:
            return
        env, w = self.env, self.world
        if not self.meta:
            from d3grasp.vocabulary import GRASP_TYPES

            e = env.world_entries[w]
            self.meta = {"object": e.id, "kind": e.kind, "grasp": GRASP_TYPES[int(env.grasp.type_id[w])]}
        f = env.view.pad_force if self.sensed else env.view.pad_force_true
        self.forces.append(np.linalg.norm(f[w].cpu().numpy(), axis=-1))
        for ep in episodes or ():
            if int(ep.get("env", -1)) == w:
                # The step that ended the episode already shows the next episode's reset state.
                self.forces.pop()
                self.outcome = ep
                self.done = True

    def plot(self, path: str | Path) -> Path:
        from d3grasp.viz.figure import pyplot, save_figure
        from d3grasp.vocabulary import PHASES

        plt = pyplot()

        if not self.forces:
            raise ValueError("no tactile samples recorded")
        env = self.env
        forces = np.stack(self.forces)  # (T, 11)
        t = (np.arange(len(forces)) + 1) * env.dt
        fig, axes = plt.subplots(4, 1, figsize=(8, 7), sharex=True)
        for ax, name, pads in zip(axes, FINGERS, FINGER_PADS, strict=True):
            for i, p in enumerate(PHASES):
                start = env.script.phase_start[p] * env.dt
                end = (
                    env.script.phase_start[PHASES[i + 1]] if i + 1 < len(PHASES) else env.max_episode_length
                ) * env.dt
                if end > start:
                    ax.axvspan(start, end, color=PHASE_SHADES[p], lw=0)
                    if ax is axes[0]:
                        ax.text(start, 1.02, p, transform=ax.get_xaxis_transform(), fontsize=7, rotation=30)
            for k, p in enumerate(pads):
                ax.plot(t, forces[:, p], label=f"pad {p} (link {k + 1 if name != 'thumb' else k + 2})")
            ax.set_ylabel(f"{name}\n|F| (N)")
            ax.legend(loc="upper right", fontsize=7)
            ax.set_xlim(0.0, max(t[-1], env.max_episode_length * env.dt))
        axes[-1].set_xlabel("time (s)")
        title = f"{self.meta.get('object')} ({self.meta.get('kind')}, {self.meta.get('grasp')} grasp)"
        if self.outcome is not None:
            o = self.outcome
            title += (
                f": grasp {'yes' if o.get('s_grasp') else 'no'}, lift {'yes' if o.get('s_lift') else 'no'}, "
                f"disturb {'yes' if o.get('s_disturb') else 'no'}"
            )
        fig.suptitle(title, y=0.995)
        return save_figure(fig, path, dpi=110)
