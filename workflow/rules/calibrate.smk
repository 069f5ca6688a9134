# Calibration: deployable estimators see only the library and the Probe-A queries.
# The parameter-nearest oracle reads hidden labels: it has its own rule (evaluation only).


checkpoint estimate:
    conda:
        "../envs/knockgs.yaml"
    input:
        library=f"{P}/descriptors/{{object}}/library.csv",
        queries=f"{P}/descriptors/{{object}}/queries_{{split}}.csv",
    output:
        json=f"{P}/estimates/{{object}}/{{split}}/{{method}}.json",
    log:
        f"logs/{PROFILE}/estimates/{{object}}/{{split}}/{{method}}.log",
    wildcard_constraints:
        method="fixed_default|response_nearest|response_knn|global_ridge|local_ridge",
    params:
        method=lambda wc: wc.method,
        options=lambda wc: config.get("method_params", {}).get(wc.method, {}),
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
        json=f"{P}/estimates/{{object}}/{{split}}/parameter_nearest_oracle.json",
    log:
        f"logs/{PROFILE}/estimates/{{object}}/{{split}}/parameter_nearest_oracle.log",
    params:
        config_hash=config_hash(),
    script:
        "../scripts/oracle_estimate.py"
