"""What the skills' training shares (`felis.learning.common`).

    evaluator.py    Evaluator: jobs run inline, in a process pool or on a Ray cluster (make_evaluator)
    checkpoints.py  save_checkpoint / load_checkpoint: the torch trainers' resumable checkpoint per epoch
    curves.py       run_epochs: the epoch loop of the torch nets and their learning curves (plot_loss_curves)
    torchstate.py   a torch model's weights as numpy arrays and back (torch_to_arrays, model_with_arrays)
    weights.py      write_weights: a weights file (.npz of float32 arrays and a JSON __meta__), atomically
    jsonable.py     jsonable: metadata (numpy, dataclasses, paths) to JSON
"""
