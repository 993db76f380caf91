"""The pipelines a session can choose, with their options (public: it holds no site data)."""

from __future__ import annotations

from fastapi import APIRouter

from edgepos.api.context import Context
from edgepos.api.convert import pipeline_to_wire
from edgepos.api.schemas import PipelineList

router = APIRouter(prefix="/v1/pipelines", tags=["pipelines"])


@router.get("", response_model=PipelineList, summary="List pipelines and their options")
async def list_pipelines(context: Context) -> PipelineList:
    """Every pipeline, its options (defaults, bounds, choices) and the measurement types it uses."""
    return PipelineList(
        pipelines=[pipeline_to_wire(context.pipelines[name]) for name in sorted(context.pipelines)]
    )
