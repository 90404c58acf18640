"""LightningCLI for omg: the data module is fixed, the model is any LightningModule by class
(short names like ``PretrainModule`` work), and the model receives the data's spec.

Each run writes into its own versioned directory: unless the config names a logger, a
CSVLogger logs to ``<default_root_dir>/version_N`` and config.yaml is saved beside its
metrics.csv, so a second run never overwrites the first. To log to Weights & Biases instead
(``offline: true`` or WANDB_MODE=offline needs no network)::

    trainer:
      logger:
        class_path: lightning.pytorch.loggers.WandbLogger
        init_args: {project: omg, save_dir: runs/NAME, offline: false}
"""

from __future__ import annotations

import lightning as L
from jsonargparse import Namespace
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI, SaveConfigCallback

import omg.callbacks  # noqa: F401  (short callback names: EvalCallback, RenderCallback)
import omg.lit  # noqa: F401  (imports the modules so short class names resolve)
from omg.callbacks.run import run_dir
from omg.data.datamodule import MotionDataModule


class SaveRunConfig(SaveConfigCallback):
    """Saves the run's config.yaml into its versioned run directory (``omg.callbacks.run_dir``)
    rather than ``trainer.log_dir``, which for wandb is a directory shared by every run."""

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if self.already_saved:
            return
        directory = run_dir(trainer)
        if trainer.is_global_zero:
            directory.mkdir(parents=True, exist_ok=True)
            self.parser.save(self.config, str(directory / self.config_filename), skip_none=False,
                             overwrite=self.overwrite, multifile=self.multifile)
        self.already_saved = trainer.strategy.broadcast(True)


class OmgLightningCLI(LightningCLI):
    def __init__(self, args: list[str] | None = None):
        super().__init__(
            model_class=L.LightningModule,
            subclass_mode_model=True,
            datamodule_class=MotionDataModule,
            parser_kwargs={"exit_on_error": False},
            save_config_callback=SaveRunConfig,
            save_config_kwargs={"overwrite": True},  # only a run without a logger shares its directory
            args=args,
        )

    def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
        parser.link_arguments("data", "model.init_args.spec", compute_fn=lambda data: data.spec, apply_on="instantiate")

    def before_instantiate_classes(self) -> None:
        """The default logger: a versioned CSVLogger in default_root_dir (Lightning's own default is
        TensorBoard when installed, in a lightning_logs/ subfolder)."""
        config = self.config[self.subcommand] if self.subcommand else self.config
        trainer = config.trainer
        if trainer.logger is None or trainer.logger is True:
            trainer.logger = Namespace(class_path="lightning.pytorch.loggers.CSVLogger",
                                       init_args=Namespace(save_dir=trainer.default_root_dir or ".", name=""))
