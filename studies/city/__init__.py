"""City scale (issue 37): the production coordinator on SUMO districts, against SUMO's own routing."""
