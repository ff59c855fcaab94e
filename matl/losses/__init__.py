"""Losses: appearance (Eq. 1-4) and metric learning (triplet Eq. 7, NCE Eq. 9)."""

from matl.losses.appearance import AppearanceLoss, MultiAnchorAppearanceLoss, anchor_distances, appearance_distance
from matl.losses.metric import NCELoss, TripletLoss

__all__ = ["AppearanceLoss", "MultiAnchorAppearanceLoss", "NCELoss", "TripletLoss", "anchor_distances",
           "appearance_distance"]
