"""Whether this process is greyid's own (its command line) or a user's (a script, a notebook).

greyid changes process-wide state only as far as its own programs need it.  Two
changes that speed up a command but would reach a user's own objects and
programs are made only in greyid's own processes ([`take_over()`][greyid._process.take_over], called by
the command line before anything else): freezing the objects of the imports
(``gc.freeze``, [`greyid._collector`][greyid._collector]) and keeping every compiled program in
JAX's persistent cache however quick it was to compile ([`greyid._jax`][greyid._jax]).
"""

_owned = {"on": False}


def take_over() -> None:
    """Say that this process runs greyid's command line (and nothing of the user's)."""
    _owned["on"] = True


def owned() -> bool:
    return _owned["on"]
