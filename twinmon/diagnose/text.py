"""The diagnosis in words: the lines ``twinmon diagnose`` prints per unit and the phrases the
report reuses (an effect's group with its members' posterior weights, the candidates the
recorded channels cannot see).

Every name comes from the :class:`~twinmon.diagnose.result.UnitGap` records (FMU parameters
and channels of the config); nothing here knows a machine.
"""
from __future__ import annotations

import math

#: Indent of the lines under a unit's first line.
INDENT = "    "


def summary_line(unit: str, g, no_candidates: str = "", hidden: bool = True) -> str:
    """What ``twinmon diagnose`` prints for one unit: a first line (verdict, the named effects
    with their estimates, where, how far the gap shrinks), then one indented line per named
    effect whose group has more than one member (:func:`group_line`) and one for the
    candidates the recorded channels cannot see (:func:`hidden_line`; left out with
    ``hidden=False``). ``no_candidates``: what to do when the config lists no candidate
    effect."""
    lines = [_first_line(unit, g, no_candidates)]
    if g.verdict == "effect":
        lines += [INDENT + group_line(grp) for grp in g.groups if len(grp["members"]) > 1]
    if hidden and g.hidden:
        lines.append(INDENT + hidden_line(g.hidden))
    return "\n".join(lines)


def noise_note(g, inside: bool = False) -> str:
    """How well the noise level the residuals are measured in is known: said only where
    diagnose estimated it from the record (one sd of the estimate, in %); ``inside`` a
    parenthesis already."""
    dof = getattr(g, "noise_dof", None)
    if not dof:
        return ""
    text = f"noise estimated from the record to +-{100.0 / math.sqrt(2.0 * dof):.0f} %"
    return f"; {text}" if inside else f" ({text})"


def _first_line(unit: str, g, no_candidates: str) -> str:
    if g.verdict == "none":
        return (f"{unit}: no significant gap (p = {g.p_gap:.2g}, residual RMS "
                f"{g.rms_before:.2f} x noise{noise_note(g, inside=True)})")
    where = (f"years {g.where_years[0]}-{g.where_years[-1]}" if g.where_years else "")
    if g.where_windows:
        where += f", {', '.join(g.where_windows)}"
    if g.verdict == "unexplained" and not g.candidates:
        return (f"{unit}: UNEXPLAINED gap from year {g.onset} ({where}); residual RMS "
                f"{g.rms_before:.2f} x noise{noise_note(g)}; "
                + (no_candidates or "no candidate effects to test (model.effects)"))
    if g.verdict == "unexplained":
        return (f"{unit}: UNEXPLAINED gap from year {g.onset} ({where}); residual RMS "
                f"{g.rms_before:.2f} x noise{noise_note(g)}; best candidate {g.candidates[0]} "
                f"would close "
                f"only {g.closed_percent:.0f} %")
    sep = ""
    if g.groups:
        # Each named effect; its group, when it has one, on a line of its own below.
        text = " + ".join(_named(grp) for grp in g.groups)
    else:
        # A gap.h5 written before groups were recorded: the first effect's group inline.
        parts = []
        for e in g.effects:
            est = g.estimate.get(e)
            parts.append(f"{e} = {est[0]:.4g} [{est[1]:.4g}, {est[2]:.4g}]" if est else e)
        text = " or ".join(parts[:len(g.group)]) if len(g.group) > 1 else parts[0]
        extra = [p for p, e in zip(parts, g.effects) if e not in g.group]
        if extra:
            text += " + " + " + ".join(extra)
        sep = (f"; {g.separating_channel} would separate the group" if g.separating_channel
               else "")
    fy = ""
    if g.failure_year_before != g.failure_year_after:
        fy = (f"; projected failure year {g.failure_year_before or 'none'} -> "
              f"{g.failure_year_after or 'none'}")
    return (f"{unit}: {text} from year {g.onset} ({where}); residual RMS "
            f"{g.rms_before:.2f} -> {g.rms_after:.2f} x noise{noise_note(g)}, "
            f"{g.closed_percent:.0f} % of "
            f"the excess gap closed, BIC gain {g.delta_bic_final:.0f}{sep}{fy}")


def _named(grp: dict) -> str:
    """A group's named effect with its estimate, and how many members the group has."""
    m = grp["members"][0]
    text = f"{m['effect']} = {m['value']:.4g} [{m['q05']:.4g}, {m['q95']:.4g}]"
    if len(grp["members"]) > 1:
        text += f" (group of {len(grp['members'])})"
    return text


def member_text(m: dict) -> str:
    """One member of a group, other than the named effect: ``b = 0.93 [0.92, 0.94] 33 %``;
    a member that explains the gap together with the named effect ``a``:
    ``a with c = 0.1 [0, 0.5] 8 %``."""
    text = f"{m['effect']} = {m['value']:.4g} [{m['q05']:.4g}, {m['q95']:.4g}]"
    if m.get("together_with"):
        text = " and ".join(m["together_with"]) + " with " + text
    return f"{text} {weight_text(m['weight'])}"


def weight_text(w: float) -> str:
    """A posterior weight as a percentage (``<1 %`` rather than ``0 %``)."""
    return "<1 %" if w < 0.005 else f"{100 * w:.0f} %"


def group_line(grp: dict) -> str:
    """A group of more than one member in one line: every member by posterior weight (the
    named one first), the channel that would separate them, and the spread of their
    projected failure years when they differ by more than a year."""
    named = grp["effect"]
    ms = grp["members"]
    text = (f"{named}'s group (the data cannot tell its members apart; posterior weight): "
            f"{named} {weight_text(ms[0]['weight'])}, "
            + ", ".join(member_text(m) for m in ms[1:]))
    if grp.get("separating_channel"):
        text += f"; recording {grp['separating_channel']} would separate them"
    if grp.get("failure_year_spread"):
        text += f"; failure year {failure_range_text(grp['failure_year_range'])} across the group"
    return text


def failure_range_text(rng: list) -> str:
    """``[earliest, latest]`` failure years (None: no failure within the horizon) in words."""
    lo, hi = rng
    if lo is None:
        return "none within the horizon"
    return f"{lo} to {hi}" if hi is not None else f"{lo} to none within the horizon"


def hidden_by_channel(hidden: dict) -> dict:
    """``{channel or None: [effect, ...]}`` of a unit's ``hidden`` record, in its order."""
    out: dict = {}
    for name, h in hidden.items():
        out.setdefault(h.get("channel"), []).append(name)
    return out


def hidden_line(hidden: dict) -> str:
    """The candidates the recorded channels cannot see, and what would show them:
    ``hidden (the degradation inputs take them up on the recorded channels): a, b;
    recording X would show them``."""
    by = hidden_by_channel(hidden)
    names = [n for ns in by.values() for n in ns]
    text = (f"hidden (the degradation inputs take {'them' if len(names) > 1 else 'it'} up "
            "on the recorded channels): ")
    if len(by) == 1:
        (ch, ns), = by.items()
        return text + ", ".join(ns) + "; " + _shown_by(ch, len(ns))
    return text + ", ".join(f"{', '.join(ns)} ({_shown_by(ch, len(ns))})"
                            for ch, ns in by.items())


def _shown_by(channel, n: int) -> str:
    it = "them" if n > 1 else "it"
    if channel is None:
        return f"no unrecorded channel of model.channels would show {it}"
    return f"recording {channel} would show {it}"
