"""LightningCLI for omg: the data module is fixed, the model is any LightningModule by class
(short names like ``PretrainModule`` work), and the model receives the data's spec."""

from __future__ import annotations

import lightning as L
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI

import omg.lit  # noqa: F401  (imports the modules so short class names resolve)
from omg.data.datamodule import MotionDataModule


class OmgLightningCLI(LightningCLI):
    def __init__(self, args: list[str] | None = None):
        super().__init__(
            model_class=L.LightningModule,
            subclass_mode_model=True,
            datamodule_class=MotionDataModule,
            parser_kwargs={"exit_on_error": False},
            save_config_kwargs={"overwrite": True},
            args=args,
        )

    def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
        parser.link_arguments("data", "model.init_args.spec", compute_fn=lambda data: data.spec, apply_on="instantiate")
