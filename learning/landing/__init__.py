"""The falling cat's landing (`felis.learning.landing`, seed 000): evolved nets, whole-body motions, the library.

    policy.py      gene units, SimpleBehaviour, ComplexBehaviour, load_policy: the policy at run time (inference)
    nets.py        random units, mutation, crossover, elimination, fitness, ranking, save_policy
    features.py    motion features, PCA and DTW motion similarity (MotionRecorder, Pca, motion_distance)
    samples.py     hand-written spine rules tuned per orientation: the motion samples (make_samples, rollout)
    config.py      TrainConfig: the evolution's settings
    task.py        one evaluation: a rollout in MuJoCo scored (evaluate_job, run_rollout, make_task)
    breeding.py    the next generation from a ranked population, ranking by eq. 10 or 11
    checkpoint.py  TrainState and its checkpoint file
    plot.py        plot_curves: the evolution's learning curves
    train.py       train_landing: the evolution (``felis train landing``)
    evaluate.py    drop experiments judged by the landed rule (LandingSim, run_drops, ``felis eval landing``)
    motion.py      an open-loop whole-body motion (MotionRule, motion files): inference
    optimum.py     the per-drop optimum: CMA-ES over whole-body motions (``--policy optimum``)
    wholebody.py   whole-body motion samples (the optimum on a sphere of orientations, samples' format)
    designs.py     other buildable cats (servos, voltage, paws): the design study
    library.py     the motion library: the shipped policy (MotionLibrary, LibraryRule, LibraryBatch): inference
    library_build.py  making it (``felis train landing-library``): optimum on a grid, robust twins, probes
"""
