"""Experiments section 17, the scoring script as run (.gpu/b/jobs/average32.py): score an average of
students and of mirrored clips with the estimator's own runtime (ad_estimator.evaluate: the node's
preprocessing and frame slots). Needs ad_estimator and ad_sim on PYTHONPATH (source env.sh).

Each view is (member model, mirrored?). Every frame is encoded once per view (a mirrored view sees
every mask of the clip mirrored left-right, as training's flip augmentation does); the head of each
view runs on its own features; class probabilities and the normalised parameters (log space for E
and yield) are averaged over views.

usage: python average.py --out DIR --title T --bags B [--mirror] MODEL [MODEL ...]
"""
import argparse
import json
import sys
from pathlib import Path

import numpy as np

from ad_estimator import metrics
from ad_estimator.evaluate import evaluate, find_bags, to_metrics
from ad_estimator.model import EstimatorModel


class Averaged:
    def __init__(self, members, mirror):
        first = members[0].info
        for m in members[1:]:
            i = m.info
            assert (i.class_names, i.parameter_names, i.input_size, i.frame_count, i.frame_interval,
                    i.previous_frames, i.mask_levels) == (first.class_names, first.parameter_names, first.input_size,
                                                         first.frame_count, first.frame_interval,
                                                         first.previous_frames, first.mask_levels), m.info.path
            assert m.feature_shape == members[0].feature_shape
        self.members, self.info = members, first
        self.views = [(m, flip) for m in members for flip in ((False, True) if mirror else (False,))]
        self.feature_shape = (len(self.views), *members[0].feature_shape)
        self.model_id = "+".join(m.model_id for m in members) + ("+mirror" if mirror else "")

    def encode(self, mask, earlier=()):
        out = []
        for model, flip in self.views:
            if flip:
                out.append(model.encode(np.ascontiguousarray(mask[:, ::-1]),
                                        [np.ascontiguousarray(e[:, ::-1]) for e in earlier]))
            else:
                out.append(model.encode(mask, earlier))
        return np.stack(out)

    def predict(self, features, valid):
        features = np.asarray(features, np.float32)
        valid = np.asarray(valid, bool)
        probabilities, params, logvars = [], [], []
        for v, (model, _) in enumerate(self.views):
            outputs = model._run(features[:, v], valid)
            z = outputs[0][0].astype(np.float64)
            p = np.exp(z - z.max())
            probabilities.append(p / p.sum())
            params.append(outputs[1][0])
            if len(outputs) > 2:
                logvars.append(outputs[2][0])
        logits = np.log(np.mean(probabilities, axis=0))
        logvar = np.mean(logvars, axis=0) if len(logvars) == len(self.views) else None
        return self.members[0]._estimate(logits, np.mean(params, axis=0), logvar, int(valid.sum()), 0.0)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("models", nargs="+", type=Path)
    p.add_argument("--bags", type=Path, required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--title", required=True)
    p.add_argument("--mirror", action="store_true")
    a = p.parse_args()
    model = Averaged([EstimatorModel.load(m) for m in a.models], a.mirror)
    counts = [25, *metrics.TEMPORAL_OOD_FRAMES]
    evaluation = evaluate(model, find_bags([a.bags]), counts, progress=False)
    by_frames = {k: to_metrics(v, model.info.parameter_names) for k, v in evaluation.predictions.items() if v}
    report = metrics.write_report(by_frames, a.out, a.title)
    (a.out / "predictions.json").write_text(metrics.json_text(
        {"model_id": model.model_id, "frames": {str(k): [vars(p) for p in v]
                                                 for k, v in evaluation.predictions.items()}}, indent=1))
    print(metrics.format_table(report, a.title))
    print(json.dumps({"problems": evaluation.problems()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
