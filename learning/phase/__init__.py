"""The gait's phase through a periodic autoencoder (`felis.learning.phase`, seed 003).

    estimator.py  PhaseEstimator: phase, frequency and amplitude online, for the balance monitor (inference)
    infer.py      PaeConfig, PaeNumpy, load_pae_numpy: the PAE encoder in numpy and its weights file (inference)
    pae.py        the torch PAE with Fourier latent dynamics (FLD), save_pae / load_pae
    data.py       GaitRecording: gait recordings from simulation or run logs, their .npz files
    train.py      train_phase: windows, sequences, Adam, checkpoints, evaluate_phase
    run.py        train_phase_run: one ``felis train phase`` run, recordings to calibrated weights and figures
    evaluate.py   phase_metrics, gate_comparison: the learned phase against the gait, and for the balance monitor
    plot.py       plot_phase: a one-page PNG of what a phase model reads from a gait
"""
