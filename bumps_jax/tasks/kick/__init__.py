"""The kick (the paper's task): the NAO kicks a ball to a target distance."""
