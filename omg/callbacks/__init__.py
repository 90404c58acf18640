"""Lightning callbacks, named in configs by ``class_path`` like every Lightning object:
generation metrics (``EvalCallback``) and previews (``RenderCallback``). Both sample through the
model's ``sample(texts, lengths, steps=, guidance=, seed=, use_ema=)`` and write into the run's
versioned directory (``run_dir``). In a config::

    trainer:
      callbacks:
        - class_path: EvalCallback
          init_args:
            evaluator: runs/evaluator/checkpoints/last.ckpt   # or {t2m: {checkpoint, glove_dir, mean_std_dir}}
            metrics: [fid, r_precision, mm_dist, diversity, multimodality, foot_skating]
            every_n_steps: 5000       # during fit: one pass on the fixed prompt set, logged as eval/<metric>
            replications: 20          # at `omg test`: mean ± 95% CI, printed and written to eval.json / eval.md
            steps: 200
        - class_path: RenderCallback
          init_args: {prompts: ["a person walks forward"], num_samples: 3, every_n_steps: 5000}
"""

from omg.callbacks.eval import EvalCallback
from omg.callbacks.habit import HabitEvalCallback
from omg.callbacks.omgpt import OODEvalCallback, SideTransferCallback
from omg.callbacks.render import RenderCallback
from omg.callbacks.run import run_dir

__all__ = ["EvalCallback", "HabitEvalCallback", "OODEvalCallback", "RenderCallback", "SideTransferCallback", "run_dir"]
