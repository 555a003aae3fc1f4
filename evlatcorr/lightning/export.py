"""Export of a trained network: fp16 safetensors, its JSON card and the folder's ``README.md``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from torch import nn

__all__ = ["export_network", "write_checkpoint_readme"]


def export_network(adapter: nn.Module, card: dict[str, Any], folder: Path, resumed: bool = False,
                   from_shipped: bool = False) -> None:
    """Write ``adapter.net`` as ``folder/<card name>.safetensors`` shards, the card as JSON, and the README.

    Args:
        adapter: the trained adapter (its ``net`` is saved).
        card: the run's card (``name``, ``command``, ``steps``, ``train_seconds``, ...); updated in place
            with ``files`` and ``sha256`` (checked at every load).
        folder: the checkpoint folder.
        resumed: the run resumed a Lightning checkpoint (its step count goes on from there).
        from_shipped: the run started from the shipped weights (its step count restarted at 0).

    A run that continues earlier weights of this name (resumed, or from the shipped weights)
    extends an existing card's history: commands, training time, note and (from the shipped
    weights) steps.
    """
    from evlatcorr.adapters.checkpoint import card_sha256, save_weights

    previous = folder / f"{card['name']}.json"
    if (resumed or from_shipped) and previous.is_file():
        old = json.loads(previous.read_text())
        card["commands"] = old.get("commands", [old["command"]]) + [card["command"]]
        card["train_seconds"] = round(card["train_seconds"] + old["train_seconds"], 1)
        if "note" in old:
            card["note"] = old["note"]
        if not resumed:  # the step count restarted on top of the shipped weights
            card["steps"] += int(old["steps"])
    files = save_weights(adapter.net, folder / f"{card['name']}.safetensors")
    card["files"] = [f.name for f in files]
    card["sha256"] = card_sha256(files)
    previous.write_text(json.dumps(card, indent=2) + "\n")
    write_checkpoint_readme(folder)


def write_checkpoint_readme(folder: str | Path) -> Path:
    """Render the JSON cards of a checkpoint folder (written by ``--export``) as its ``README.md``."""
    folder = Path(folder)
    cards = [json.loads(p.read_text()) for p in sorted(folder.glob("*.json")) if not p.name.endswith(".index.json")]
    lines = [
        "# Shipped weights",
        "",
        "Trained here by `python -m evlatcorr.train` on the simulator's training photographs "
        "(`evlatcorr.simulate.PHOTOGRAPHS_TRAIN`, disjoint from the benchmark's test photographs), ideal events, "
        "L1 loss; validated on other simulated sequences of the same training photographs. fp16 safetensors, "
        "sharded at 15 MB; the adapters load them with `checkpoint=\"default\"` "
        "(REFID: `REFIDAdapter(checkpoint=\"default\", m=4, n=1)`). Each `<name>.json` holds every detail.",
        "",
        "Each card lists the SHA-256 of its weight files under `sha256`; every load checks them (a corrupt or "
        "modified file raises a ValueError naming it). `pip install .` installs this folder as "
        "`evlatcorr/checkpoints/`, where `checkpoint=\"default\"` finds it.",
        "",
        "| name | model | steps | train time | device | val PSNR (blurry input) | val SSIM | files |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for c in cards:
        lines.append(f"| {c['name']} | {c['model']} | {c['steps']} | {c['train_seconds'] / 60:.0f} min | "
                     f"{c['device']} | {c['val_psnr']:.2f} dB ({c['val_blurry_psnr']:.2f} dB) | {c['val_ssim']:.3f} | "
                     f"{len(c.get('files', []))} |")
    # Data settings shared by every card once, then what differs per checkpoint.
    shared = {k: v for k, v in cards[0]["data"].items() if all(c["data"].get(k) == v for c in cards)} if cards else {}
    lines += ["", "Data: " + ", ".join(f"{k}={v}" for k, v in shared.items()), ""]
    for c in cards:
        own = {k: v for k, v in c["data"].items() if k not in shared}
        if own:
            lines.append(f"- {c['name']}: " + ", ".join(f"{k}={v}" for k, v in own.items()))
        if c.get("note"):
            lines.append(f"- {c['name']}: {c['note']}")
    lines += ["", "Commands, in order (run from the repository root):", ""]
    for c in cards:
        for command in c.get("commands", [c["command"]]):
            lines.append(f"    {command}")
    path = folder / "README.md"
    path.write_text("\n".join(lines) + "\n")
    return path
