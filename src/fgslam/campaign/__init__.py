"""Monte Carlo campaigns on Dask: worlds x seeds x config variants, one seeded simulation and
comparison per task, results appended to JSONL (resumable) and summarised across seeds.

Dask is imported only when a campaign runs (the ``dask`` extra); the spec, the task function and
the aggregation work without it.
"""

from fgslam.campaign.aggregate import aggregate, describe, summary_markdown, write_summary
from fgslam.campaign.execute import CampaignRun, dask_client, require_dask, run_campaign
from fgslam.campaign.results import ResultStore, read_records
from fgslam.campaign.spec import (
    CampaignError,
    CampaignSpec,
    expand,
    parse_overrides,
    parse_seeds,
    variants_from_sweeps,
)
from fgslam.campaign.task import run_task

__all__ = [
    "CampaignError", "CampaignRun", "CampaignSpec", "ResultStore", "aggregate", "dask_client", "describe",
    "expand", "parse_overrides", "parse_seeds", "read_records", "require_dask", "run_campaign", "run_task",
    "summary_markdown", "variants_from_sweeps", "write_summary",
]
