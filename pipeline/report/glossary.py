"""The report's glossary: the terms its tables and sentences use, each in one or two plain sentences.

Written once here and rendered as the report's "Terms used in this report" section.
"""

from __future__ import annotations

from pipeline.methods import method_label
from pipeline.report.analysis import PRIMARY_ENDPOINT
from pipeline.report.document import Section, Table

__all__ = ["glossary_section"]

_E = PRIMARY_ENDPOINT

#: (term, meaning) in the order a reader meets them
TERMS = (
    ("vote", "The teacher's pseudo-mask of an image: a pixel is spacecraft when at least half of the teacher's "
             "prompts mark it.  The students are trained on it; scored as a predictor, it is a reference point."),
    ("gate", "The reliability gate g of a training image, from 0 to 1: how far its prompts agree, how many of "
             "them gave a usable mask and how plausible the mask's area is, multiplied.  Stage II weights the "
             "image's geometry terms by g, so at g = 0 they are off."),
    ("ceiling", "The supervised ceiling: the Plain Student's recipe trained on the reference (hand-drawn) masks "
                "instead of the vote.  It is not annotation-free; it shows how far true labels would get."),
    ("noise floor", "How far a difference between two methods moves under a purely numerical change (another "
                    "thread count or precision), measured by the stability benchmark.  A difference is "
                    "claimed only when its confidence interval clears it."),
    ("primary endpoint", f"The one comparison fixed before the results were seen: {_E.group}, "
                         f"{method_label(_E.treatment)} − {method_label(_E.control)}, Image IoU at the "
                         "threshold calibrated on the validation images.  It is tested on its own; every other "
                         "difference is exploratory and corrected for the number of comparisons."),
    ("lockbox", "A test group kept aside until the method is frozen and then evaluated once, so that no choice "
                "was tuned on it."),
    (_E.group, "A test group of spacecraft seen in neither training nor validation, named as in "
               "SpaceSense-Bench; the paper's lockbox, and the group of the primary endpoint."),
)


def glossary_section() -> Section:
    """Render the report's glossary (:data:`TERMS`) as one two-column table.

    Returns
    -------
    Section
        The "Terms used in this report" section.
    """
    return Section("Terms used in this report",
                   [Table("tab:glossary", "Terms", ["Term", "Meaning"], [[t, m] for t, m in TERMS])])
