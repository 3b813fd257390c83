"""Learning (`felis.learning`): one subpackage per skill, and what they share.

- `landing/` — the falling cat's landing (seed 000): `policy` (inference: inputs, gene units,
  behaviours, the evolved nets), `nets` (operators, fitness, ranking, saving), `features` (motion
  features, DTW), `samples` (spine-rule motion samples), `config`, `task`, `breeding`, `checkpoint`,
  `plot` and `train` (the evolution), `evaluate` (drops judged), `motion`, `optimum`, `wholebody`, `designs`
  (whole-body motions, the per-drop optimum, other cats), `library` and `library_build` (the motion library:
  the shipped policy).
- `ik/` — the arm's learned IK (seed 001): `solver` and `infer` (inference: the pipeline, numpy nets,
  weights), `data` and `corpus` (demonstrations), `net` and `train` (torch nets, training), `run` (a
  training run), `evaluate`. The posture rule and the trajectories are `felis.controllers.arm_posture`
  and `felis.controllers.trajectories`.
- `phase/` — the gait's phase (seed 003): `estimator` and `infer` (inference: the numpy PAE encoder, the
  online estimator), `pae` (torch PAE and FLD), `data` (gait recordings), `train`, `run`, `evaluate`, `plot`.
- `balance/` — the strategy selector (seed 004): `selector` (inference: case base, kNN selector),
  `compare` (the SVM, accuracies), `evaluate` (push experiments), `train`.
- `common/` — `evaluator` (process pool or Ray), `checkpoints`, `curves` (the epoch loop and learning
  curves of the torch nets), `torchstate` and `weights` (torch weights as numpy arrays, the weights file),
  `jsonable` (metadata to JSON).

Controllers import only the inference modules (numpy, no torch, no simulation); training, data and
evaluation modules may import controllers and the simulation. Shipped weights are in `weights/`.
"""
