"""Lightning training of the latency polynomial and of the restoration networks, one concern per module.

=========================  ===============================================================================
module                     owns
=========================  ===============================================================================
``base``                   :class:`EventFramesModule`: moves ``EventFrames`` batches to devices
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

from evlatcorr.lightning.base import EventFramesModule
from evlatcorr.lightning.data import (
    EventFramesDataModule,
    FramesDataset,
    RandomCrops,
    collate_event_frames,
    frames_loader,
    seed_worker,
)
from evlatcorr.lightning.export import export_network, write_checkpoint_readme
from evlatcorr.lightning.latency import LatencyCorrectionModule
from evlatcorr.lightning.latency_data import recording_training_frames, simulated_training_frames
from evlatcorr.lightning.networks import MODELS, build_adapter, checkpoint_name
from evlatcorr.lightning.restoration import CorrectedRestorationModule, RestorationModule
from evlatcorr.lightning.restoration_data import RecordingRestorationData, SimulatedRestorationData
from evlatcorr.lightning.targets import has_truth, restoration_pair

__all__ = [
    "EventFramesModule",
    "EventFramesDataModule",
    "FramesDataset",
    "RandomCrops",
    "collate_event_frames",
    "frames_loader",
    "seed_worker",
    "export_network",
    "write_checkpoint_readme",
    "LatencyCorrectionModule",
    "recording_training_frames",
    "simulated_training_frames",
    "MODELS",
    "build_adapter",
    "checkpoint_name",
    "CorrectedRestorationModule",
    "RestorationModule",
    "RecordingRestorationData",
    "SimulatedRestorationData",
    "has_truth",
    "restoration_pair",
]
