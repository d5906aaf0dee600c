"""``python -m evaluation``: the evaluation of docs/evaluation-protocol.md
(``evaluation.evaluate``)."""

from evaluation.evaluate import main

if __name__ == "__main__":
    main()
