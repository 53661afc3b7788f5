# Tables 1-3, the GT-quality table, figures, and the report items.


report: "../report/workflow.rst"


rule tables:
    input:
        evals=expand("results/eval/{method}.parquet", method=METHODS),
        framesets="results/dataset/framesets.parquet",
        rde="results/rde/framesets.parquet",
        quality="results/dataset/gt_quality.csv",
    output:
        table1=report("results/tables/table1.md", caption="../report/table1.rst", category="Tables"),
        table1_csv="results/tables/table1.csv",
        table2=report("results/tables/table2.md", caption="../report/table2.rst", category="Tables"),
        table2_csv="results/tables/table2.csv",
        table3=report("results/tables/table3.md", caption="../report/table3.rst", category="Tables"),
        table3_csv="results/tables/table3.csv",
        table2_paired=report("results/tables/table2_paired.md", caption="../report/table_paired.rst", category="Tables"),
        table2_paired_csv="results/tables/table2_paired.csv",
        table3_paired=report("results/tables/table3_paired.md", caption="../report/table_paired.rst", category="Tables"),
        table3_paired_csv="results/tables/table3_paired.csv",
        quality=report("results/tables/table_gt_quality.md", caption="../report/table_gt_quality.rst", category="Tables"),
        quality_csv="results/tables/table_gt_quality.csv",
    params:
        kinds=KINDS,
    conda:
        ENV
    log:
        "logs/tables.log",
    script:
        "../scripts/tables.py"


rule figures:
    input:
        framesets="results/dataset/framesets.parquet",
        evals=expand("results/eval/{method}.parquet", method=METHODS),
        predictions=expand("results/eval/predictions/{method}", method=[m for m in METHODS if m != "input"]),
        logs=expand("results/models/{model}/loss_log.csv", model=EVALUATED_MODELS),
    output:
        comparison=report("results/figures/comparison.png", caption="../report/comparison.rst", category="Figures"),
        curves=report(expand("results/figures/training_{model}.png", model=EVALUATED_MODELS), caption="../report/training.rst",
                      category="Figures", subcategory="Training curves"),
    params:
        methods=[m for m in METHODS if m != "input"],
        models=EVALUATED_MODELS,
        split=SETTINGS.evaluation.split,
        frames_per_scene=SETTINGS.evaluation.figure_frames_per_scene,
    conda:
        ENV
    log:
        "logs/figures.log",
    script:
        "../scripts/figures.py"


rule run_config:
    output:
        report("results/report/config.yaml", caption="../report/config.rst", category="Configuration"),
    params:
        config=config,
    conda:
        ENV
    log:
        "logs/run_config.log",
    script:
        "../scripts/run_config.py"


rule report:
    input:
        rules.tables.output,
        rules.figures.output,
        rules.run_config.output,
