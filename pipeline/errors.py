"""The one error type of bad input: its message names the file and the record."""


class DataError(ValueError):
    def __init__(self, source: str, record: str, problem: str):
        self.source, self.record, self.problem = str(source), record, problem
        super().__init__(f"{source}: {record}: {problem}")

    def __reduce__(self):
        # from a --workers process to cli prepare whole: pickled by its message alone, it cannot be rebuilt
        # (three arguments), which left the pool waiting for ever
        return type(self), (self.source, self.record, self.problem)
