"""The learning loop's picture: success of the learned and the scripted Pick (alone and in the
whole task, mean ± std over the held-out seeds) and the training loss per epoch."""

from __future__ import annotations

from pathlib import Path


def plot_loop(summary: dict, path: Path) -> None:
    import matplotlib.pyplot as plt
    fig = loop_figure(summary)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def loop_figure(summary: dict):
    """The picture of :func:`plot_loop`, a matplotlib figure (the caller closes it)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    evaluation = summary["evaluation"]
    fig, (bars, curve) = plt.subplots(1, 2, figsize=(10, 4))
    width = 0.38
    for k, (name, colour) in enumerate((("scripted", "tab:gray"), ("learned", "tab:blue"))):
        result = evaluation[name]
        means = [result[what]["success_mean"] for what in ("skill", "task")]
        stds = [result[what]["success_std"] for what in ("skill", "task")]
        xs = [i + (k - 0.5) * width for i in range(2)]
        bars.bar(xs, means, width, yerr=stds, capsize=4, color=colour, label=name)
        for x, m in zip(xs, means):
            bars.text(x, min(m, 1.0) + 0.02, f"{m:.2f}", ha="center", fontsize=9)
    bars.set_xticks([0, 1], ["Pick alone", "whole task"])
    bars.set_ylim(0, 1.25)
    bars.set_ylabel(f"success rate (seeds {evaluation['seeds']}, mean ± std)")
    bars.legend(loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=2, frameon=False)   # above the bars
    training = summary["training"]
    curve.semilogy(range(1, len(training["loss_per_epoch"]) + 1), training["loss_per_epoch"])
    curve.set_xlabel("epoch")
    curve.set_ylabel("training loss (normalised MSE)")
    curve.set_title(f"{training['samples']} frames, {training['episodes']} episodes, {training['seconds']:.0f} s",
                    fontsize=10)
    fig.suptitle(f"Pick by behaviour cloning ({summary['collected']['episodes']} episodes collected) vs scripted")
    fig.tight_layout()
    return fig
