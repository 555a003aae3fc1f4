"""Lightning training of the latency polynomial and of the restoration networks, one concern per module.

=========================  ===============================================================================
module                     owns
=========================  ===============================================================================
``base``                   :class:`EventFramesModule`: the base of the trainers, its batches ``EventFrames``
``data``                   datasets, seeded random crops, loaders, :class:`EventFramesDataModule`
``latency``                :class:`LatencyCorrectionModule` (self-supervised latency polynomial)
``latency_data``           training samples of the polynomial (simulated frames, tiles of a recording)
``networks``               :data:`MODELS`, :func:`build_adapter`, :func:`checkpoint_name`
``targets``                :func:`has_truth`, :func:`restoration_pair` (what a batch is scored against)
``restoration``            :class:`RestorationModule`, :class:`CorrectedRestorationModule`
``restoration_data``       :class:`SimulatedRestorationData`, :class:`RecordingRestorationData`
``export``                 fp16 safetensors, cards and README of exported networks
``cli``                    the command line ``python -m evlatcorr.lightning {latency,restore}``
``latency_command``        the ``latency`` subcommand
``restore_command``        the ``restore`` subcommand
``arguments``              command-line pieces the subcommands share
=========================  ===============================================================================
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from evlatcorr._lazy import lazy_attributes

_ORIGINS = {
    "EventFramesModule": "evlatcorr.lightning.base",
    "EventFramesDataModule": "evlatcorr.lightning.data",
    "FramesDataset": "evlatcorr.lightning.data",
    "RandomCrops": "evlatcorr.lightning.data",
    "collate_event_frames": "evlatcorr.lightning.data",
    "frames_loader": "evlatcorr.lightning.data",
    "seed_worker": "evlatcorr.lightning.data",
    "export_network": "evlatcorr.lightning.export",
    "write_checkpoint_readme": "evlatcorr.lightning.export",
    "LatencyCorrectionModule": "evlatcorr.lightning.latency",
    "recording_training_frames": "evlatcorr.lightning.latency_data",
    "simulated_training_frames": "evlatcorr.lightning.latency_data",
    "MODELS": "evlatcorr.lightning.networks",
    "build_adapter": "evlatcorr.lightning.networks",
    "checkpoint_name": "evlatcorr.lightning.networks",
    "CorrectedRestorationModule": "evlatcorr.lightning.restoration",
    "RestorationModule": "evlatcorr.lightning.restoration",
    "RecordingRestorationData": "evlatcorr.lightning.restoration_data",
    "SimulatedRestorationData": "evlatcorr.lightning.restoration_data",
    "has_truth": "evlatcorr.lightning.targets",
    "restoration_pair": "evlatcorr.lightning.targets",
}

__all__ = list(_ORIGINS)

__getattr__, __dir__ = lazy_attributes(__name__, _ORIGINS)

if TYPE_CHECKING:  # what type checkers and IDEs see (`X as X`: re-exported)
    from evlatcorr.lightning.base import EventFramesModule as EventFramesModule
    from evlatcorr.lightning.data import EventFramesDataModule as EventFramesDataModule
    from evlatcorr.lightning.data import FramesDataset as FramesDataset
    from evlatcorr.lightning.data import RandomCrops as RandomCrops
    from evlatcorr.lightning.data import collate_event_frames as collate_event_frames
    from evlatcorr.lightning.data import frames_loader as frames_loader
    from evlatcorr.lightning.data import seed_worker as seed_worker
    from evlatcorr.lightning.export import export_network as export_network
    from evlatcorr.lightning.export import write_checkpoint_readme as write_checkpoint_readme
    from evlatcorr.lightning.latency import LatencyCorrectionModule as LatencyCorrectionModule
    from evlatcorr.lightning.latency_data import recording_training_frames as recording_training_frames
    from evlatcorr.lightning.latency_data import simulated_training_frames as simulated_training_frames
    from evlatcorr.lightning.networks import MODELS as MODELS
    from evlatcorr.lightning.networks import build_adapter as build_adapter
    from evlatcorr.lightning.networks import checkpoint_name as checkpoint_name
    from evlatcorr.lightning.restoration import CorrectedRestorationModule as CorrectedRestorationModule
    from evlatcorr.lightning.restoration import RestorationModule as RestorationModule
    from evlatcorr.lightning.restoration_data import RecordingRestorationData as RecordingRestorationData
    from evlatcorr.lightning.restoration_data import SimulatedRestorationData as SimulatedRestorationData
    from evlatcorr.lightning.targets import has_truth as has_truth
    from evlatcorr.lightning.targets import restoration_pair as restoration_pair
