"""The arm's learned inverse kinematics (`felis.learning.ik`, seed 001).

    solver.py    IkSolver: targets -> Motion Predictor -> Posture Estimator -> filter -> refinement (inference)
    infer.py     NetSpec, NumpyNet, load_weights: the nets in numpy and their weights file (inference)
    data.py      demonstration trajectories (make_corpus), the train/validation/test split, network windows
    corpus.py    corpora as .npz (save_corpus, load_corpus) and demonstrations from run logs (recorded_demos)
    net.py       SeqNet: the torch LSTM / MLP nets, save_weights
    train.py     train_net: Adam, checkpoints, the best-validation weights
    run.py       train_ik: one ``felis train ik`` run, corpus to weights and results
    evaluate.py  evaluate: accuracy, limits, smoothness, latency and posture of the pipeline on trajectories
"""
