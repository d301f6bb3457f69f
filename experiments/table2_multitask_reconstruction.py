"""Table 2: texture reconstruction, multi-task vs single-task MTSA-UNet.

    python experiments/table2_multitask_reconstruction.py --preset small --seeds 0 1 2

The paper's protocol: the single-task reconstruction model is Stage I-1 alone (all frames, no
labels); the multi-task model continues with Stage I-2 (soft multi-task: CE + 0.1 x
reconstruction, every branch trainable). Both rows of a seed share the same I-1 run.
The third row is the single-task control at equal length: Stage I-1 trained on for as many
optimizer steps as the multi-task run's I-1 + I-2 (on the protocol, 78 + 2,500), so that a
multi-task advantage is not one of training time.
"""

from irdepth_experiments.runner import RECON_COLUMNS, Arm, Table, main

TABLE = Table(
    name="table2_multitask_reconstruction",
    title="Table 2: texture reconstruction, multi-task vs single-task",
    about=("Reconstruction of the camera's 8-bit image from the raw frame (SSIM, PSNR against "
           "ir8 / 255; entropy of the 8-bit reconstruction). Single-task = Stage I-1 only; "
           "multi-task = Stage I-1 then soft multi-task Stage I-2 (the paper's protocol, "
           "section 4.4). Both start from the same I-1 weights of a seed. Single-task at equal "
           "length = Stage I-1 trained for as many optimizer steps as the multi-task run's "
           "I-1 + I-2 (the control for training time)."),
    arms=(Arm("multi-task (I-1 + I-2)", "stage1"),
          Arm("single-task (I-1 only)", "stage1_i1"),
          Arm("single-task (I-1, as many steps)", "stage1_i1", equal_steps=True)),
    columns=RECON_COLUMNS,
    paper={"multi-task": dict(ssim=0.869, psnr=28.481, entropy=7.377),
           "single-task": dict(ssim=0.529, psnr=15.456, entropy=6.859)},
)

if __name__ == "__main__":
    main(TABLE)
