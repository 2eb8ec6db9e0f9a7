import time, sys
from pathlib import Path
from physmend.config import compose
from physmend.problem import load_problem
from physmend.ude import train, evaluate
tm = sys.modules["physmend.ude.train"]

def test_time(user_project: Path):
    base = ["model=oscillator", "data=oscillator", "train.epochs=6", "train.eval_every=2", "ude.width=4",
          "train.step=0.1", "train.segment_length=5"]
    for extra in ([], ["simulate.method=dopri5"], ["simulate.rtol=1e-3", "simulate.atol=1e-3"], ["train.step=0.2", "train.segment_length=10", "train.epochs=4"], ["ude.output_scale=1e300"]):
        ov = base + extra
        cfg = compose(ov, user_config_dir=user_project / "my_conf")
        problem = load_problem(cfg)
        t0 = time.time()
        ref = tm.reference(problem, cfg)
        t1 = time.time()
        try:
            res = train(cfg, problem)
            r = res.val_rmse
        except Exception as e:
            r = repr(e)
        print(extra, "ref", round(t1-t0, 2), "train", round(time.time()-t1, 2), r)
