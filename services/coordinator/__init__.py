"""Cloud coordinator service: merged traffic maps and route plans for connected vehicles."""
