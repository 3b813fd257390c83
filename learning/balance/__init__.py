"""Reactive-strategy selection after a push (`felis.learning.balance`, seed 004).

    selector.py  CaseBase, denoise, KnnSelector, load_selector: the inference module controllers import (numpy)
    compare.py   SvmSelector (the paper's SVM, scikit-learn) and the accuracies of any selector
    evaluate.py  push experiments on the simulated cat (run_pushes, demonstrate): verdicts, reactions, demos
    train.py     fit_selector: the shipped selector from demonstrations (``felis train balance``), push_demo
"""
