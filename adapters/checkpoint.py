"""Loading and saving model weights for the adapters.

:func:`load_weights` reads the formats the downstream models are released in and the one we ship:

* BasicSR (EFNet, REFID): a ``torch.save`` dict with ``"params"`` (preferred) or ``"params_ema"``;
* Lightning ``.ckpt``: ``{"state_dict": {"model.<key>": ...}, ...}``;
* a plain state_dict ``.pth`` / ``.pt`` (also inside ``"model"``, ``"net"``, ``"model_state_dict"``);
* our ``.safetensors``, single or sharded (see below).

Key prefixes are reconciled automatically: a prefix such as ``model.``, ``net.`` or ``module.`` on the
checkpoint's keys is stripped (keys outside it, e.g. a Lightning module's loss network, are ignored), or
the module's own prefix is added (loading a bare network checkpoint into a wrapper). Floating point
tensors are cast to the dtype of the parameter they load into (fp16 shards load into fp32 modules).

Sharding scheme (written by :func:`save_weights`, read by :func:`load_weights`): weights that fit in
``max_shard_mb`` go to the single file ``<stem>.safetensors``. Otherwise they go to
``<stem>-00001-of-0000N.safetensors`` ... ``<stem>-0000N-of-0000N.safetensors`` beside it, plus an index
``<stem>.safetensors.index.json`` in the Hugging Face format (``{"metadata": {...}, "weight_map":
{key: shard file name}}``); ``<stem>.safetensors`` itself is then not written. ``load_weights`` accepts
``<stem>.safetensors`` (falling back to its index or shards when the file is absent), the index, or any
one shard (the whole set is read).

Verification (every read): a file that cannot be read (truncated, corrupt, another format, a broken pickle,
an index that does not match its shards) raises a ``ValueError`` naming it, a missing file or shard a
``FileNotFoundError``. Floating point tensors holding NaN or inf are refused (``check_finite=False`` to load
them anyway). When a card ``<stem>.json`` beside the weights lists a file under ``"sha256"`` (``{file name:
hex digest}``, written with :func:`card_sha256`; the shipped cards in ``checkpoints/`` do), the file's SHA-256
must match before it is read. The file names and these checks are in :mod:`evlatcorr.adapters.checkpoint_files`.
"""

from __future__ import annotations

import json
import pickle
import warnings
import zipfile
from collections.abc import Mapping
from pathlib import Path

import torch
from torch import Tensor, nn

from evlatcorr.adapters.checkpoint_files import (
    INDEX_SUFFIX,
    SHARD_PATTERN,
    card_sha256,
    check_finite_weights,
    file_sha256,
    stem_of,
    verify_listed_sha256,
)
from evlatcorr.locations import checkpoint_dirs
from evlatcorr.sample_warnings import user_stacklevel

__all__ = ["card_sha256", "checkpoint_dirs", "file_sha256", "load_state_dict_file", "load_weights",
           "resolve_checkpoint", "save_weights"]

_NESTED_KEYS = ("params", "params_ema", "state_dict", "model_state_dict", "model", "net", "network")
_MAX_LISTED = 10
MB = 1_000_000  # max_shard_mb counts decimal megabytes
_Index = tuple[Path, dict[str, str]]  # a safetensors index file and its weight_map


# reading ----------------------------------------------------------------------------------------
def _shard_files(stem_path: Path) -> list[Path]:
    """The complete shard set ``<stem>-XXXXX-of-NNNNN.safetensors`` beside ``stem_path`` (empty if none)."""
    stem = stem_path.name
    groups: dict[int, list[Path]] = {}
    if stem_path.parent.is_dir():
        for f in stem_path.parent.iterdir():
            m = SHARD_PATTERN.match(f.name)
            if m and m.group("stem") == stem:
                groups.setdefault(int(m.group("total")), []).append(f)
    if not groups:
        return []
    if len(groups) > 1:
        raise ValueError(f"several shard sets of {stem_path} (totals {sorted(groups)}); "
                         "delete the stale ones")
    total, files = next(iter(groups.items()))
    files = sorted(files)
    have = {int(SHARD_PATTERN.match(f.name).group("index")) for f in files}  # type: ignore[union-attr]
    if have != set(range(1, total + 1)):
        missing = sorted(set(range(1, total + 1)) - have)
        raise FileNotFoundError(f"incomplete shard set {stem_path}-*-of-{total:05d}.safetensors: "
                                f"shards {missing} are missing")
    return files


def _load_safetensors(files: list[Path], index: _Index | None = None,
                      check_finite: bool = True) -> dict[str, Tensor]:
    """Read (and verify) the shards ``files``; ``index`` (its path and weight map) must agree with them."""
    from safetensors.torch import load_file

    state: dict[str, Tensor] = {}
    origin: dict[str, str] = {}
    for f in files:
        verify_listed_sha256(f)
        try:
            part = load_file(str(f), device="cpu")
        except FileNotFoundError:
            raise FileNotFoundError(f"checkpoint not found: {f}") from None
        except Exception as exc:  # SafetensorError (truncated, bad header), OSError (unreadable), ...
            raise ValueError(f"cannot read {f}: {str(exc).rstrip('.')}. The file is truncated, corrupt or not a "
                             "safetensors file") from exc
        dup = state.keys() & part.keys()
        if dup:
            raise ValueError(f"key {sorted(dup)[0]!r} appears in more than one shard ({f})")
        if check_finite:
            check_finite_weights(part, f)
        state.update(part)
        origin.update(dict.fromkeys(part, f.name))
    if index is not None:
        index_path, weight_map = index
        wrong = [f"{k} (listed in {name}, found in {origin.get(k, 'no shard')})"
                 for k, name in weight_map.items() if origin.get(k) != name]
        wrong += [f"{k} (in {origin[k]}, not listed)" for k in origin if k not in weight_map]
        if wrong:
            raise ValueError(f"{index_path} does not match its shards ({len(wrong)} keys): {_short(wrong)}")
    return state


def _read_index(path: Path) -> _Index:
    """Verify and parse a ``.safetensors.index.json``: its path and its ``weight_map``."""
    verify_listed_sha256(path)
    try:
        index = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:  # ValueError: JSONDecodeError, UnicodeDecodeError
        raise ValueError(f"cannot read the safetensors index {path}: {exc}") from exc
    weight_map = index.get("weight_map") if isinstance(index, dict) else None
    if not isinstance(weight_map, dict) or not weight_map:
        raise ValueError(f"{path} is not a safetensors index (no 'weight_map')")
    bad = sorted({repr(v) for v in weight_map.values()
                  if not isinstance(v, str) or Path(v).name != v or not v.endswith(".safetensors")})
    if bad:
        raise ValueError(f"{path} lists invalid shard file names (expected *.safetensors beside it): "
                         f"{_short(bad)}")
    return path, weight_map


def _resolve_safetensors(path: Path) -> tuple[list[Path], _Index | None] | None:
    """The safetensors file(s) ``path`` names and the index that lists them (if read), or None when ``path``
    is not a safetensors path."""
    if path.name.endswith(INDEX_SUFFIX) and path.is_file():
        index = _read_index(path)
        files = [path.parent / name for name in sorted(set(index[1].values()))]
        absent = [f.name for f in files if not f.is_file()]
        if absent:
            raise FileNotFoundError(f"{path} lists shard files that do not exist: {_short(absent)}")
        return files, index
    if SHARD_PATTERN.match(path.name) and path.is_file():
        return _shard_files(stem_of(path)), None
    if path.name.endswith(".safetensors"):
        if path.is_file():
            return [path], None
        index_path = path.with_name(path.name + ".index.json")
        if index_path.is_file():
            return _resolve_safetensors(index_path)
        shards = _shard_files(stem_of(path))
        if shards:
            return shards, None
        raise FileNotFoundError(f"checkpoint not found: {path} (nor its index {index_path.name} nor shards "
                                f"{stem_of(path).name}-XXXXX-of-NNNNN.safetensors)")
    return None


def _safetensors_files(path: Path) -> list[Path] | None:
    """Resolve ``path`` to the safetensors file(s) it names, or None when it is not a safetensors path."""
    resolved = _resolve_safetensors(path)
    return None if resolved is None else resolved[0]


def _first_line(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {lines[0].rstrip('.') if lines else ''}"


def _torch_load(path: Path) -> object:
    try:
        with path.open("rb") as f:
            head = f.read(9)
        is_zip = zipfile.is_zipfile(path)
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc}") from exc
    # torch.save writes a zip archive (legacy format: a pickle, protocol >= 2, which starts with 0x80)
    if not is_zip and not (len(head) >= 2 and head[0] == 0x80):
        hint = ""
        if len(head) == 9 and head[8:9] == b"{" and int.from_bytes(head[:8], "little") < path.stat().st_size:
            hint = " (it looks like a safetensors file: name it *.safetensors)"
        raise ValueError(f"{path} is not a torch.save checkpoint (neither a zip archive nor a pickle): it is "
                         f"truncated, corrupt or in another format{hint}")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        warnings.warn(f"{path} holds more than tensors ({str(exc).splitlines()[0]}); loading it with "
                      "weights_only=False, which runs its pickled code: only load checkpoints you trust",
                      stacklevel=user_stacklevel())
        try:
            return torch.load(path, map_location="cpu", weights_only=False)
        except Exception as exc2:  # a corrupt pickle raises anything (KeyError, EOFError, ...)
            raise ValueError(f"cannot read {path}: {_first_line(exc2)}. The file is truncated, corrupt or not a "
                             "torch.save checkpoint") from exc2
    except Exception as exc:  # RuntimeError (a corrupt zip), KeyError / EOFError (a corrupt pickle), ...
        raise ValueError(f"cannot read {path}: {_first_line(exc)}. The file is truncated, corrupt or not a "
                         "torch.save checkpoint") from exc


def _is_state_dict(obj: object) -> bool:
    return isinstance(obj, Mapping) and len(obj) > 0 and all(
        isinstance(k, str) and isinstance(v, Tensor) for k, v in obj.items())


def _extract_state_dict(obj: object, path: Path, key: str | None) -> dict[str, Tensor]:
    if isinstance(obj, nn.Module):
        return dict(obj.state_dict())
    if key is not None:
        if not isinstance(obj, Mapping) or key not in obj:
            found = list(obj.keys())[:_MAX_LISTED] if isinstance(obj, Mapping) else type(obj).__name__
            raise ValueError(f"{path} has no entry {key!r}; it has {found}")
        obj = obj[key]
        if isinstance(obj, nn.Module):
            return dict(obj.state_dict())
    if _is_state_dict(obj):
        return dict(obj)  # type: ignore[arg-type]
    if isinstance(obj, Mapping):
        for k in _NESTED_KEYS:
            if k in obj and _is_state_dict(obj[k]):
                return dict(obj[k])
            if k in obj and isinstance(obj[k], nn.Module):
                return dict(obj[k].state_dict())
        # a state_dict may also hold a few non-tensor entries (e.g. BatchNorm counters saved as ints)
        tensors = {k: v for k, v in obj.items() if isinstance(k, str) and isinstance(v, Tensor)}
        if tensors and len(tensors) >= 0.9 * len(obj):
            return tensors
        raise ValueError(f"{path} holds no recognisable state_dict; top-level keys: "
                         f"{_short([str(k) for k in obj.keys()])} "
                         f"(expected a state_dict or one of {_NESTED_KEYS})")
    raise ValueError(f"{path} holds a {type(obj).__name__}, not a state_dict")


def load_state_dict_file(path: str | Path, key: str | None = None, *,
                         check_finite: bool = True) -> dict[str, Tensor]:
    """Read a checkpoint file into a flat ``{name: tensor}`` dict on the CPU (no prefix handling), verified.

    Each file read is first compared with the SHA-256 its card lists, when a card ``<stem>.json`` beside it
    lists one (see :func:`card_sha256`), and its floating point tensors are checked for NaN and inf.

    Args:
        path: a ``.safetensors`` file, shard or index, or a ``torch.save`` file (``.pth``, ``.pt``,
            ``.ckpt``).
        key: the entry of a ``torch.save`` dict that holds the weights; by default the first of
            ``params, params_ema, state_dict, model_state_dict, model, net, network`` found, or the
            dict itself when it is a state_dict.
        check_finite: refuse floating point tensors holding NaN or inf.

    Returns:
        the tensors by name, as stored (dtype kept).

    Raises:
        FileNotFoundError: when the file (or a shard of it) does not exist.
        ValueError: naming the file, when it cannot be read (truncated, corrupt, not a checkpoint, a broken
            pickle, an index that does not match its shards), does not match the SHA-256 its card lists,
            holds a non-finite tensor (also naming its key) or holds no state_dict.

    Example:
        >>> import tempfile, os
        >>> with tempfile.TemporaryDirectory() as d:
        ...     files = save_weights(nn.Linear(2, 3), os.path.join(d, "lin.safetensors"))
        ...     state = load_state_dict_file(files[0])
        >>> {k: tuple(v.shape) for k, v in state.items()}
        {'bias': (3,), 'weight': (3, 2)}
    """
    path = Path(path).expanduser()
    resolved = _resolve_safetensors(path)
    if resolved is not None:
        return _load_safetensors(*resolved, check_finite=check_finite)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    verify_listed_sha256(path)
    state = _extract_state_dict(_torch_load(path), path, key)
    if check_finite:
        check_finite_weights(state, path)
    return state


# matching keys ---------------------------------------------------------------------------------
def _prefixes(keys: list[str], max_depth: int = 3) -> set[str]:
    out = set()
    for k in keys:
        parts = k.split(".")
        for d in range(1, min(max_depth, len(parts) - 1) + 1):
            out.add(".".join(parts[:d]) + ".")
    return out


def _match_prefix(state: dict[str, Tensor], target: set[str]) -> dict[str, Tensor]:
    """Rename ``state`` keys (strip one prefix, or add one) so that most of them are in ``target``."""
    keys = list(state)
    best_score = sum(k in target for k in keys)
    best = state
    if best_score == len(keys) == len(target):
        return state
    for prefix in sorted(_prefixes(keys), key=len):
        renamed = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
        score = sum(k in target for k in renamed)
        if score > best_score:
            best_score, best = score, renamed
    for prefix in sorted(_prefixes(list(target)), key=len):
        renamed = {prefix + k: v for k, v in state.items()}
        score = sum(k in target for k in renamed)
        if score > best_score:
            best_score, best = score, renamed
    return best


def _short(items: list[str]) -> str:
    if len(items) <= _MAX_LISTED:
        return ", ".join(items)
    return ", ".join(items[:_MAX_LISTED]) + f", ... ({len(items) - _MAX_LISTED} more)"


def load_weights(module: nn.Module, path: str | Path, strict: bool = True, *, key: str | None = None,
                 check_finite: bool = True) -> None:
    """Load a checkpoint into ``module`` in place, after verifying it (see :func:`load_state_dict_file`).

    Args:
        module: the network (or a wrapper around it: a missing prefix such as ``net.`` is added).
        path: BasicSR ``.pth`` (``params`` / ``params_ema``), Lightning ``.ckpt`` (``state_dict`` with a
            ``model.`` / ``net.`` prefix), a plain state_dict, or our (sharded) ``.safetensors``.
        strict: raise when keys are missing or unexpected. Shape mismatches always raise.
        key: the entry of a ``torch.save`` dict holding the weights (see :func:`load_state_dict_file`).
        check_finite: refuse checkpoints whose floating point tensors hold NaN or inf.

    Raises:
        FileNotFoundError: when the checkpoint (or a shard of it) does not exist.
        ValueError: naming the file when it cannot be read, is corrupt (SHA-256 mismatch with its card,
            non-finite tensors) or holds no state_dict; listing the missing, unexpected and mis-shaped keys
            when they do not match.

    Example:
        >>> net = nn.Linear(2, 3)
        >>> import tempfile, os
        >>> with tempfile.TemporaryDirectory() as d:
        ...     files = save_weights(net, os.path.join(d, "lin.safetensors"))
        ...     load_weights(nn.Linear(2, 3), files[0])
    """
    state = load_state_dict_file(path, key=key, check_finite=check_finite)
    own = module.state_dict()
    state = _match_prefix(state, set(own))
    missing = [k for k in own if k not in state]
    unexpected = [k for k in state if k not in own]
    mis_shaped = [f"{k}: checkpoint {tuple(v.shape)} vs module {tuple(own[k].shape)}"
                  for k, v in state.items() if k in own and v.shape != own[k].shape]
    if mis_shaped or (strict and (missing or unexpected)):
        lines = [f"checkpoint {path} does not match {type(module).__name__}:"]
        if missing and strict:
            lines.append(f"  missing keys ({len(missing)}): {_short(missing)}")
        if unexpected and strict:
            lines.append(f"  unexpected keys ({len(unexpected)}): {_short(unexpected)}")
        if mis_shaped:
            lines.append(f"  shape mismatches ({len(mis_shaped)}): {_short(mis_shaped)}")
        raise ValueError("\n".join(lines))
    cast = {}
    for k, v in state.items():
        if k not in own:
            continue
        target = own[k]
        cast[k] = v.to(target.dtype) if v.is_floating_point() and target.is_floating_point() else v
    module.load_state_dict(cast, strict=strict)


# writing ---------------------------------------------------------------------------------------
def save_weights(module: nn.Module, path: str | Path, dtype: torch.dtype | None = torch.float16,
                 max_shard_mb: float = 15) -> list[Path]:
    """Write ``module``'s state_dict as safetensors, sharded so that each file is at most ``max_shard_mb``.

    Args:
        module: the network.
        path: ``<dir>/<stem>.safetensors``; see the module docstring for the shard names. Earlier files
            of the same stem (single file, index, shards) are removed first.
        dtype: floating point tensors are cast to this dtype (``None`` keeps them); others are kept.
        max_shard_mb: largest file size in decimal megabytes (10^6 bytes).

    Returns:
        the files written (the shards, then the index when sharded). Record ``card_sha256(files)`` under
        ``"sha256"`` in the card ``<stem>.json`` beside them to have every load verify them.

    Raises:
        ValueError: when ``path`` does not end in ``.safetensors`` or one tensor alone exceeds the limit.
    """
    from safetensors.torch import save_file

    path = Path(path).expanduser()
    if not path.name.endswith(".safetensors") or SHARD_PATTERN.match(path.name):
        raise ValueError(f"path must be <stem>.safetensors (not a shard name), got {path.name!r}")
    if max_shard_mb <= 0:
        raise ValueError(f"max_shard_mb must be positive, got {max_shard_mb}")
    limit = int(max_shard_mb * MB)
    state: dict[str, Tensor] = {}
    for k, v in module.state_dict().items():
        v = v.detach().cpu()
        if dtype is not None and v.is_floating_point():
            v = v.to(dtype)
        state[k] = v.contiguous().clone()  # clone: safetensors refuses tensors that share storage

    # greedy packing in state_dict order; each tensor costs its bytes plus its header entry
    header_base = 1024
    shards: list[dict[str, Tensor]] = [{}]
    size = header_base
    for k, v in state.items():
        cost = v.numel() * v.element_size() + len(k) + 128
        if cost + header_base > limit:
            raise ValueError(f"tensor {k!r} ({cost / MB:.1f} MB) is larger than max_shard_mb={max_shard_mb}")
        if size + cost > limit and shards[-1]:
            shards.append({})
            size = header_base
        shards[-1][k] = v
        size += cost

    stem = stem_of(path)
    index_path = path.with_name(path.name + ".index.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    for old in [path, index_path, *(f for f in path.parent.iterdir()
                                    if (m := SHARD_PATTERN.match(f.name)) and m.group("stem") == stem.name)]:
        if old.is_file():
            old.unlink()
    metadata = {"format": "pt", "module": type(module).__name__}
    if len(shards) == 1:
        save_file(shards[0], str(path), metadata=metadata)
        return [path]
    written, weight_map = [], {}
    for i, shard in enumerate(shards, start=1):
        f = path.with_name(f"{stem.name}-{i:05d}-of-{len(shards):05d}.safetensors")
        save_file(shard, str(f), metadata=metadata)
        written.append(f)
        weight_map.update({k: f.name for k in shard})
    total = sum(v.numel() * v.element_size() for v in state.values())
    index = {"metadata": {"total_size": total, **metadata}, "weight_map": weight_map}
    index_path.write_text(json.dumps(index, indent=1) + "\n")
    written.append(index_path)
    return written


# finding shipped checkpoints (where: evlatcorr.locations.checkpoint_dirs) ---------------------------------
def resolve_checkpoint(name_or_path: str | Path | None, model_name: str) -> Path | None:
    """Turn an adapter's ``checkpoint`` argument into a file for :func:`load_weights`.

    Args:
        name_or_path: ``None`` (random initialisation: returns ``None``), ``"default"`` (the weights shipped
            as ``checkpoints/<model_name>*.safetensors``, see :func:`checkpoint_dirs`), or a path.
        model_name: e.g. ``"efnet"``.

    Returns:
        the path to load (a file, shard or index), or ``None``.

    Raises:
        FileNotFoundError: when the path, or the default checkpoint, does not exist.
        ValueError: when several different default checkpoints match, or a safetensors index is unreadable or
            does not match the SHA-256 its card lists (the weights themselves are verified by
            :func:`load_weights`).

    Example:
        >>> resolve_checkpoint(None, "efnet") is None
        True
    """
    if name_or_path is None:
        return None
    if str(name_or_path) != "default":
        path = Path(name_or_path).expanduser()
        if path.is_file():
            return path
        if path.name.endswith(".safetensors") and _safetensors_files_or_none(path):
            return path
        raise FileNotFoundError(f"checkpoint for {model_name} not found: {path}")
    searched = checkpoint_dirs()
    for d in searched:
        if not d.is_dir():
            continue
        candidates = [*d.glob(f"{model_name}*.safetensors"), *d.glob(f"{model_name}*{INDEX_SUFFIX}")]
        # "<model>-<variant>" stems (refid-4-1, refid-deblur) belong to other layouts: exact name only
        stems = sorted({stem_of(f).name for f in candidates} - {s for s in (stem_of(f).name for f in candidates)
                                                                   if s.startswith(f"{model_name}-")})
        if not stems:
            continue
        if model_name in stems:
            stem = model_name
        elif len(stems) == 1:
            stem = stems[0]
        else:
            raise ValueError(f"several default checkpoints for {model_name} in {d}: {stems}; "
                             "pass one as a path")
        single = d / f"{stem}.safetensors"
        index = d / f"{stem}{INDEX_SUFFIX}"
        if single.is_file():
            return single
        if index.is_file():
            return index
        return _shard_files(d / stem)[0]
    raise FileNotFoundError(
        f"no default checkpoint for {model_name}: no {model_name}*.safetensors in "
        f"{', '.join(str(d) for d in searched)}. Train them with `python -m evlatcorr.train` or pass "
        f"checkpoint=<path> (official .pth / Lightning .ckpt / .safetensors), or checkpoint=None for random weights")


def _safetensors_files_or_none(path: Path) -> list[Path] | None:
    try:
        return _safetensors_files(path)
    except FileNotFoundError:
        return None
