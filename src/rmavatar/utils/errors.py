"""The one error type that means "the user's input is wrong"."""


class UserError(Exception):
    """An error caused by the user's input: the CLI prints its message without a traceback."""


PICKLE_REFUSED = ("it holds pickled Python objects, which rmavatar never unpickles (they can run code); "
                  "save plain arrays or tensors")


def load_error(exc: BaseException) -> str:
    """The reason a file failed to load, for a message. numpy's and torch's own texts about pickles
    recommend switching numpy's or torch's pickle guard off, which would let a hostile file run code: those
    are replaced by a reason that recommends nothing of the kind."""
    import pickle

    text = str(exc)
    if isinstance(exc, pickle.UnpicklingError) or "allow_pickle" in text or "weights_only" in text:
        return PICKLE_REFUSED
    return text.strip().splitlines()[0] if text.strip() else type(exc).__name__
