"""What people write and labcal reads: plans, station files, settings, readings files.

Every model is validated once, when its file is read; every mistake is one line naming the file and
the field.
"""
