"""Table 3: semantic segmentation, multi-task vs single-task MTSA-UNet.

    python experiments/table3_multitask_segmentation.py --preset small --seeds 0 1 2

The paper's protocol: the single-task segmentation model starts from the Stage I-1 weights and
trains with cross-entropy only (`stage1.multitask=False`: no reconstruction / gradient loss, and
the reconstruction / gradient branches frozen; the encoder and the segmentation branch train
with the Stage I-2 rates). Both rows of a seed share the same I-1 run.
"""

from irdepth_experiments.runner import SEG_COLUMNS, Arm, Table, main

TABLE = Table(
    name="table3_multitask_segmentation",
    title="Table 3: semantic segmentation, multi-task vs single-task",
    about=("mIoU over the six classes on the labelled test frames. Multi-task = soft multi-task "
           "Stage I-2 (CE + 0.1 x reconstruction); single-task = the same I-2 training with "
           "cross-entropy only and the auxiliary branches frozen (`stage1.multitask=false`), "
           "both from the same I-1 weights."),
    arms=(Arm("multi-task", "stage1"),
          Arm("single-task", "stage1", ("stage1.multitask=false",))),
    columns=SEG_COLUMNS,
    paper={"multi-task": dict(miou=0.6313), "single-task": dict(miou=0.5492)},
    paper_note=("Paper (private dataset; orientation only; its table 3 says 0.5492, its text "
                "0.5092 for single-task)"),
)

if __name__ == "__main__":
    main(TABLE)
