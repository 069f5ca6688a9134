# Calibration: deployable estimators see only the library and the Probe-A queries.
# The parameter-nearest oracle reads hidden labels: it has its own rule (evaluation only).
# Method names and their options: knockgs_core.calibration (METHOD_NAMES, METHOD_OPTIONS).


checkpoint estimate:
    """Every deployable method of the config on one split's tables, one file a method (one job:
    an estimate costs less than the job's start)."""
    conda:
        "../envs/knockgs.yaml"
    input:
        library=f"{P}/descriptors/{{object}}/library.csv",
        queries=f"{P}/descriptors/{{object}}/queries_{{split}}.csv",
    output:
        json=[f"{P}/estimates/{{object}}/{{split}}/{m}.json" for m in CONFIG_DEPLOYABLE],
    log:
        f"logs/{PROFILE}/estimates/{{object}}/{{split}}.log",
    params:
        methods=CONFIG_DEPLOYABLE,
        options={m: config["method_params"].get(m, {}) for m in CONFIG_DEPLOYABLE},
        config_hash=config_hash(),
    script:
        "../scripts/estimate.py"


checkpoint oracle_estimate:
    conda:
        "../envs/knockgs.yaml"
    input:
        library=f"{P}/descriptors/{{object}}/library.csv",
        targets="config/targets.csv",
    output:
        json=f"{P}/estimates/{{object}}/{{split}}/{ORACLE_METHOD}.json",
    log:
        f"logs/{PROFILE}/estimates/{{object}}/{{split}}/{ORACLE_METHOD}.log",
    params:
        options=config["method_params"].get(ORACLE_METHOD, {}),
        config_hash=config_hash(),
    script:
        "../scripts/oracle_estimate.py"
