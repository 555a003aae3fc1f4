"""The files of a checkpoint and their checks: the names of a sharded ``.safetensors`` set, its card
``<stem>.json`` with the SHA-256 of each weight file, and the checks every read makes (the listed digest, finite
weights). :mod:`evlatcorr.adapters.checkpoint` reads and writes the weights themselves."""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Iterable, Mapping
from pathlib import Path

import torch
from torch import Tensor

__all__ = ["INDEX_SUFFIX", "SHARD_PATTERN", "card_path", "card_sha256", "check_finite_weights", "file_sha256",
           "listed_sha256", "stem_of", "verify_listed_sha256"]

SHARD_PATTERN = re.compile(r"^(?P<stem>.+)-(?P<index>\d{5})-of-(?P<total>\d{5})\.safetensors$")
INDEX_SUFFIX = ".safetensors.index.json"
_SHA256_RE = re.compile(r"[0-9a-fA-F]{64}")


def stem_of(path: Path) -> Path:
    """``dir/name.safetensors`` / ``dir/name.safetensors.index.json`` / a shard -> ``dir/name``."""
    name = path.name
    m = SHARD_PATTERN.match(name)
    if m:
        return path.with_name(m.group("stem"))
    if name.endswith(INDEX_SUFFIX):
        return path.with_name(name[: -len(INDEX_SUFFIX)])
    if name.endswith(".safetensors"):
        return path.with_name(name[: -len(".safetensors")])
    return path


def file_sha256(path: str | Path) -> str:
    """The SHA-256 of a file's bytes as 64 lowercase hex digits, the hash a checkpoint card lists per file.

    A card is the ``<stem>.json`` beside the weights (``checkpoints/efnet.json`` for ``efnet-*.safetensors``);
    its ``"sha256"`` entry maps file names to this digest, and
    :func:`~evlatcorr.adapters.checkpoint.load_state_dict_file` compares it before reading each file it lists.

    Args:
        path: the file.

    Returns:
        the hex digest.

    Raises:
        FileNotFoundError: when the file does not exist.
        ValueError: when it cannot be read (a folder, no permission, an I/O error).

    Example:
        >>> import tempfile, os
        >>> with tempfile.TemporaryDirectory() as d:
        ...     with open(os.path.join(d, "abc.bin"), "wb") as f:
        ...         _ = f.write(b"abc")
        ...     file_sha256(os.path.join(d, "abc.bin"))
        'ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad'
    """
    path = Path(path).expanduser()
    digest = hashlib.sha256()
    try:
        with path.open("rb") as f:
            while block := f.read(1 << 20):
                digest.update(block)
    except FileNotFoundError:
        raise FileNotFoundError(f"checkpoint not found: {path}") from None
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc}") from exc
    return digest.hexdigest()


def card_sha256(files: Iterable[str | Path]) -> dict[str, str]:
    """The ``"sha256"`` entry of a checkpoint card: ``{file name: SHA-256}`` of each weight file in ``files``.

    Call it on what :func:`~evlatcorr.adapters.checkpoint.save_weights` returned and store it in the card
    ``<stem>.json`` written beside the weights; :func:`~evlatcorr.adapters.checkpoint.load_state_dict_file` then
    verifies every listed file before reading it. An index (``*.safetensors.index.json``) is left out: it is text,
    whose line endings git may rewrite on checkout, and its ``weight_map`` is checked against the shards on load
    instead.

    Args:
        files: the files written (shards, the single file, the index).

    Returns:
        the digests of the ``.safetensors`` (and ``torch.save``) files, by file name.

    Raises:
        FileNotFoundError: when a file does not exist.

    Example:
        >>> import tempfile, os
        >>> from torch import nn
        >>> from evlatcorr.adapters.checkpoint import save_weights
        >>> with tempfile.TemporaryDirectory() as d:
        ...     files = save_weights(nn.Linear(2, 3), os.path.join(d, "lin.safetensors"))
        ...     entry = card_sha256(files)
        >>> list(entry), len(entry["lin.safetensors"])
        (['lin.safetensors'], 64)
    """
    return {Path(f).name: file_sha256(f) for f in files if not str(f).endswith(".json")}


def card_path(path: Path) -> Path:
    """The card of a checkpoint file: ``<dir>/<stem>.json`` (the stem of its shard set, or of a ``.pth``)."""
    stem = stem_of(path)
    return path.with_name((stem.name if stem != path else path.stem) + ".json")


def listed_sha256(path: Path) -> tuple[Path, str] | None:
    """The card beside ``path`` and the SHA-256 it lists for ``path``, or None when no card lists one."""
    card = card_path(path)
    if card == path or not card.is_file():
        return None
    try:
        meta = json.loads(card.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:  # ValueError: JSONDecodeError, UnicodeDecodeError
        raise ValueError(f"cannot read {card}, the checkpoint card of {path}: {exc}") from exc
    hashes = meta.get("sha256") if isinstance(meta, dict) else None
    if not isinstance(hashes, dict) or path.name not in hashes:
        return None
    expected = hashes[path.name]
    if not isinstance(expected, str) or not _SHA256_RE.fullmatch(expected):
        raise ValueError(f"checkpoint card {card} lists an invalid SHA-256 for {path.name}: {expected!r} "
                         "(expected 64 hex digits)")
    return card, expected.lower()


def verify_listed_sha256(path: Path) -> None:
    """Compare ``path`` with the SHA-256 its card lists (nothing to do when no card lists one)."""
    listed = listed_sha256(path)
    if listed is None:
        return
    card, expected = listed
    actual = file_sha256(path)
    if actual != expected:
        raise ValueError(f"{path} is corrupt or modified: its SHA-256 is {actual} but its card {card.name} lists "
                         f"{expected}. Restore the file (reinstall evlatcorr, or copy / export it again); if you "
                         f"replaced it on purpose, update its entry under 'sha256' in {card}")


def check_finite_weights(state: Mapping[str, Tensor], path: Path) -> None:
    """Raise when a floating point tensor of ``state`` (read from ``path``) holds NaN or inf.

    One reduction per tensor: a sum is finite only if every element is (NaN propagates, inf + -inf is NaN),
    and summing in float32 (float64 for float64) is several times faster on the CPU than ``isfinite`` on
    fp16. Only a non-finite sum, which a large but finite tensor may also give by overflow, is counted
    element by element.
    """
    for k, v in state.items():
        if not (v.is_floating_point() or v.is_complex()) or v.numel() == 0:
            continue
        if v.is_complex():
            exact = v
        else:
            acc = torch.float64 if v.dtype == torch.float64 else torch.float32
            exact = v if v.dtype in (torch.float16, torch.bfloat16, torch.float32, torch.float64) else v.to(acc)
            if bool(torch.isfinite(exact.sum(dtype=acc))):
                continue
        bad = v.numel() - int(torch.isfinite(exact).sum())
        if bad:
            raise ValueError(f"{path} holds non-finite values (NaN or inf) in tensor {k!r}: {bad} of {v.numel()} "
                             "elements. The file is corrupt, or the weights diverged in training; pass "
                             "check_finite=False to load it anyway")
