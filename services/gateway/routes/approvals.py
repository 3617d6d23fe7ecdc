"""/approvals: skills waiting for an operator's approval (per vehicle and skill class, set on the reasoner),
and the decision that lets one run or makes the policy choose again."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path

from services.gateway.deps import Authorized, FleetDep
from services.gateway.errors import ApiError, responses
from services.gateway.models import ApprovalDecisionIn, ApprovalDecisionOut, ApprovalOut
from shared.errors import BusError
from shared.keys import Keys
from shared.messages import ApprovalDecision

router = APIRouter(prefix="/approvals", tags=["approvals"])

ApprovalId = Annotated[str, Path(pattern=r"^[A-Za-z0-9_-]{1,64}$", examples=["appr-0123456789ab"])]


@router.get("", response_model=list[ApprovalOut], dependencies=[Authorized], summary="Pending approvals",
            responses=responses(401))
async def pending(fleet: FleetDep) -> list[ApprovalOut]:
    """Skills the policy chose that wait for an operator, oldest first, with the policy's reasoning."""
    return [ApprovalOut(**a.model_dump(include=set(ApprovalOut.model_fields))) for a in fleet.pending_approvals()]


@router.post("/{approval_id}", response_model=ApprovalDecisionOut, dependencies=[Authorized],
             summary="Approve or reject a pending skill", responses=responses(401, 404, 409, 422, 503))
async def decide(approval_id: ApprovalId, body: ApprovalDecisionIn, fleet: FleetDep) -> ApprovalDecisionOut:
    """Approve (the skill runs) or reject (recorded in the History as rejected by the operator, with the
    reason; the policy chooses again)."""
    found = next((a for a in fleet.pending_approvals() if a.approval_id == approval_id), None)
    if found is None:
        raise ApiError(404, f"approval {approval_id} is not pending (decided, expired or unknown); GET /approvals")
    decision = ApprovalDecision(approval_id=approval_id, approved=body.approve, reason=body.reason,
                                operator=body.operator)
    try:
        reply = await fleet.bus.query(Keys(found.vehicle_id).decide_approval, decision, timeout=5.0)
    except BusError as exc:
        raise ApiError(503, f"the reasoner of {found.vehicle_id} did not answer: {exc}")
    if not reply.accepted:
        raise ApiError(409, reply.reason)
    return ApprovalDecisionOut(approval_id=approval_id, vehicle_id=found.vehicle_id, approved=body.approve)
