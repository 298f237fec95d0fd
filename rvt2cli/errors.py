"""User-facing errors.

A `UserError` is a problem with the user's input or environment (a bad file, an unknown task, no GPU).
The CLI prints it as one line, `rvt2: error: ...`, and exits with code 2, without a traceback.
Library code raises it with a message that names the file and says how to fix the problem.
"""


class UserError(Exception):
    exit_code = 2
