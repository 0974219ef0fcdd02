"""``python -m vid2sim.predictor.make_template [--out FILE] [--iterations N] [--shapes S] [--seed S] ...``:
train the template skinning network (:func:`vid2sim.predictor.template.train_template`) and write it (by
default over the shipped ``template_skinning.pt``). ``--help`` lists the settings."""

from vid2sim.predictor.template import main

if __name__ == "__main__":
    raise SystemExit(main())
